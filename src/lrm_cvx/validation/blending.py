"""How far to trust a model's dynamics: the blend towards the memoryless model
(:func:`blend_dynamics`) and its choice by forward-chaining validation (:func:`select_dynamics`,
the paired rule of :func:`~lrm_cvx.validation.search.paired_choice`)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import xarray as xr

from .._validation import as_generator
from ..errors import ModelError
from .designs import SET_KINDS
from .refits import clone_model, training_values, validation_view
from .search import HeldOutCells, PairedGuard, RollingOrigin, search, selection_table

__all__ = ["blend_dynamics", "unblended_dynamics", "memoryless_cov", "select_dynamics",
           "dynamics_alpha"]


def blend_dynamics(dynamics: Any, alpha: float, stationary_cov: Any) -> Any:
    """Dynamics shrunk towards the memoryless model with the blend of
    :mod:`~lrm_cvx.glrm.dynamics` (``A_a = alpha A``, ``Q_a = (1 - alpha^2) S + alpha^2 Q``,
    ``S`` the memoryless prior covariance). ``alpha = 1`` keeps the estimate, ``alpha = 0`` is
    the memoryless model exactly (every forecast is the prior ``N(mean, S)``; for ``"ar1"``
    with ``S = cov(X_)`` that is the empirical prior). Blends compose: ``blend`` records the
    product with the fit's own validated blend."""
    from dataclasses import replace

    from ..glrm.dynamics import blend_moments

    a = float(alpha)
    if not 0.0 <= a <= 1.0:
        raise ModelError(f"alpha must be in [0, 1], got {alpha!r}")
    A, Q = blend_moments(dynamics.A, dynamics.Q, np.asarray(stationary_cov, dtype=np.float64), a)
    return replace(dynamics, A=A, Q=0.5 * (Q + Q.T),
                   blend=float(getattr(dynamics, "blend", 1.0)) * a)


def dynamics_alpha(model: Any) -> float | None:
    """The blend :func:`select_dynamics` chose for ``model`` (its saved
    ``dynamics_selection_``), or None when it has not run."""
    table = getattr(model, "dynamics_selection_", None)
    return None if table is None else float(table.attrs["choice_alpha"])


def unblended_dynamics(model: Any) -> Any:
    """The model's dynamics re-estimated from ``X_`` without the fit's validated blend
    (``validation=None``; same kind, shrinkage, error correction and initial belief): the
    starting point of :func:`select_dynamics`."""
    from ..glrm.dynamics import estimate

    dyn = model.dynamics_
    X = model.X
    xa = model.X_
    times = xa[xa.dims[1]] if hasattr(xa, "dims") else np.arange(X.shape[1])
    return estimate(dyn.kind, X, times, shrinkage=dyn.shrinkage,
                    initial_cov=dyn.initial_cov, validation=None,
                    error_cov=getattr(dyn, "error_cov", None))


def memoryless_cov(model: Any, dynamics: Any) -> np.ndarray:
    """``(k, k)`` the latent covariance of the memoryless model that ``dynamics`` blend
    towards: the empirical covariance of ``X_`` for ``"ar1"``, else the stationary one."""
    from ..belief.posterior import empirical_moments

    if dynamics.kind == "ar1":
        return empirical_moments(model.X)[1]
    return dynamics.stationary_cov()


def select_dynamics(model: Any, data: Any, *, alphas: Sequence[float] = (0.0, 0.25, 0.5, 0.75,
                                                                          0.9, 1.0),
                    n_val: int | None = None, n_folds: int = 2, confidence: float = 1.645,
                    tolerance: float = 0.01,
                    sizes: Sequence[int] = (5, 15, 50),
                    kinds: Sequence[str] = SET_KINDS, apply: bool = True,
                    seed: Any = 0) -> tuple[float, xr.Dataset]:
    """Choose how far to trust the model's dynamics on validation snapshots.

    ``n_folds`` forward-chaining validation windows of ``n_val`` snapshots each (default a
    fifth of ``data``, at least 3; the last window ends at the last training snapshot, the
    others precede it): for each window a copy of the model is refitted (with its
    ``temporal``) on the snapshots before it, its dynamics re-estimated *without* the fit's
    own blend (:func:`unblended_dynamics`), and for each ``alpha`` the filter with
    :func:`blend_dynamics` runs through the window, one campaign per sample-set size and kind
    (the same random cells for every ``alpha``). The candidates are ``alphas``, 0
    (memoryless) and the blend the fit chose itself (``dynamics_.blend``). On a region of
    more than ``refits.VALIDATION_MAX_CELLS`` cells the refits and campaigns read one window
    of it (:func:`~lrm_cvx.validation.refits.validation_view`).

    **Rule (validated, with a guard on harm).** For each ``alpha`` and size the per-day
    differences ``d_t = mse_alpha(t) - mse_0(t)`` (validation days of every window, averaged
    over the set kinds) give the relative change ``mean(d) / mean(mse_0)`` and its upper
    confidence bound ``+ confidence * se(d) / mean(mse_0)`` (one-sided; 1.645: 95 %). A blend
    is *admissible* when that bound is at most ``tolerance`` at every size (it is then, with
    95 % confidence, at most ``tolerance`` worse than memoryless anywhere); ``alpha = 0`` (the
    memoryless model, bound 0) always is. Among the admissible blends the one with the lowest
    worst validation MSE ratio over the sizes is chosen. Data whose persistence is weak, or
    does not carry over between periods, keep (nearly) the memoryless model.
    ``confidence=0, tolerance=inf`` is the plain worst-ratio rule.

    With ``apply`` the model's ``dynamics_`` becomes the *unblended* estimate blended by
    ``alpha`` (so ``dynamics_.blend == alpha``: this rule replaces the fit's, the two never
    compose; the table is then ``model.dynamics_selection_``, saved with the model). Returns
    ``(alpha, table)``: the table of every validated choice
    (:func:`~lrm_cvx.validation.search.selection_table`) over ``candidate`` (labels ``"0.5"``,
    coordinate ``alpha``) and ``size``: ``mse``, ``ratio``, ``ucb``, ``admissible`` and
    ``total`` (the validation MSE summed over windows, days and kinds); attributes
    ``choice``, ``choice_alpha``, ``n_days``, ``confidence``, ``tolerance``.
    """

    dyn = getattr(model, "dynamics_", None)
    if dyn is None:
        raise ModelError("select_dynamics needs a model fitted with temporal='ar1' or "
                         "'seasonal' (it has no dynamics_)")
    view, data, _ = validation_view(model, data)  # a large region: a window of it
    region, V = training_values(view, data)
    T = V.shape[0]
    n_val = max(3, T // 5) if n_val is None else int(n_val)
    if not 2 <= n_val <= T - 3:
        raise ModelError(f"n_val must be in [2, {T - 3}] for {T} snapshots, got {n_val}")
    n_folds = int(n_folds)
    if n_folds < 1:
        raise ModelError(f"n_folds must be >= 1, got {n_folds}")
    n_folds = max(1, min(n_folds, (T - 3) // n_val))  # each refit keeps >= 3 snapshots
    confidence = float(confidence)
    if not (np.isfinite(confidence) and confidence >= 0):
        raise ModelError(f"confidence must be a finite number >= 0, got {confidence!r}")
    tolerance = float(tolerance)
    if not tolerance >= 0:
        raise ModelError(f"tolerance must be a number >= 0, got {tolerance!r}")
    alphas = sorted({0.0, round(float(dyn.blend), 12), *(float(a) for a in alphas)})
    sizes = [int(s) for s in sizes]
    rng = as_generator(seed)
    from ..belief.filter import LatentFilter

    windows = RollingOrigin(n_val, n_folds).split(T)
    # the sample sets of every window, the latest window's first (the same random cells for
    # every alpha); every observed cell a set leaves is scored
    holdout = HeldOutCells(max_scored=region.n_cells)
    sets = {w: {(size, kind): [holdout.split(region, np.isfinite(V[w[0] + i]), size, kind, rng)
                               for i in range(n_val)] for size in sizes for kind in kinds}
            for w in windows[::-1]}

    def day_errors(window: tuple[int, int]) -> dict[float, np.ndarray]:
        """Per alpha the day MSE ``(size, day)`` through ``window`` (set kinds averaged)."""
        lo, end = window
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sub = clone_model(view).fit(data.isel(time=slice(None, lo)), region=region)
        sub.calibration_ = None
        sub_dyn = unblended_dynamics(sub)
        S = memoryless_cov(sub, sub_dyn)
        Vv, times = V[lo:end], data["time"].values[lo:end]
        err = np.zeros((len(alphas), len(sizes), n_val))
        for a_i, alpha in enumerate(alphas):
            d = blend_dynamics(sub_dyn, alpha, S)
            for (size, _kind), cell_sets in sets[window].items():
                state = LatentFilter.from_model(sub, dynamics=d)
                for i, t in enumerate(times):
                    cells, held = cell_sets[i]
                    state.assimilate((cells, Vv[i, cells]), time=t)
                    mean, _ = state.posterior.predict(cells=held)
                    err[a_i, sizes.index(size), i] += float(np.mean((mean - Vv[i, held]) ** 2))
        return dict(zip(alphas, err / len(kinds), strict=True))

    # alpha 0 (memoryless) is the reference: the rule of every validated choice
    _, E, decision = search(day_errors, windows,
                            PairedGuard(confidence, tolerance, "select_dynamics"))
    alpha = alphas[decision.choice]
    total = xr.DataArray(np.nansum(E, axis=-1), dims=("candidate", "size"),
                         attrs={"long_name": "validation MSE summed over the days"})
    table = selection_table(
        decision, [f"{a:g}" for a in alphas], sizes, reference="memoryless (alpha 0)",
        what="mean validation-day MSE of the filter's map", data_vars={"total": total},
        coords={"alpha": ("candidate", alphas)}, choice_alpha=float(alpha),
        n_days=int(decision.n_cases), confidence=confidence, tolerance=tolerance)
    if apply:
        base_dyn = unblended_dynamics(model)
        model.dynamics_ = blend_dynamics(base_dyn, alpha, memoryless_cov(model, base_dyn))
        model.dynamics_selection_ = table  # saved with the model; read by calibrate's refits
    return alpha, table
