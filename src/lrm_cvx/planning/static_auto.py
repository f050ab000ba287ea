"""A static placement criterion that validates itself: ``place_sensors(model, n,
training=snapshots)`` / ``criterion="auto"``.

Which criterion places sensors best for the recommended fold-in is an empirical question: the
fold-in's training risk + exchange beats PySensors' QR on most records, but on a 6-hourly
storm over land the total posterior variance (``"gp-variance"``) does and the risk does not.
So :func:`select_criterion` answers it on the user's own training snapshots, as
``GLRM(temporal="auto")`` does for the temporal model (``validation/selection.py``):

* **Rolling origin.** Up to :data:`AUTO_WINDOWS` forward windows of ``h`` snapshots each (a
  tenth of the training, between :data:`AUTO_MIN_BLOCK` and :data:`AUTO_MAX_BLOCK`), the last
  ones of the training, each with at least :data:`AUTO_MIN_FIT` snapshots before it. For each
  window the model is refitted on the snapshots *before* it (same class and parameters,
  ``type(model)(**get_params())``, memoryless, uncalibrated, on the model's region; a rank or
  kernel the model validated is kept, the kernel's parameters refitted), and every
  candidate places ``n`` sensors from that refit and those snapshots only. No candidate ever
  sees the snapshots it is scored on, nor anything after the training.
* **Candidates** (:data:`AUTO_CANDIDATES`): ``"risk"`` with the recommended exchange rule,
  ``"gp-variance"`` + exchange and the ``"gp-variance"`` greedy (the last two need the
  model's spatial residual).
* **Score**: the MSE of the recommended fold-in (``fold_in_maps`` of the refit's
  ``latent_prior("empirical", spatial=True)``, kriging on) from the sensors' values, over
  every cell with a value of the held-out snapshots (mean over cells, then over snapshots and
  windows; data units^2): the predictor ``bench_placement.py`` scores with.
* **Rule, with a guard.** ``"risk"`` (the recommended criterion) stays unless another
  candidate is surely better: the one-sided upper confidence bound (:data:`AUTO_CONFIDENCE`
  standard errors) of its MSE change against risk is below 0; among those, the lowest score
  wins. The criterion is then run on the full model and training. **The unit of the guard is
  the window**, not the snapshot: a placement is fixed within a window, so the snapshots of one
  window share one draw of each candidate's placement, and their spread says nothing about how
  much the placement itself varies with the training. The change is paired per window (the
  window's mean MSE minus risk's), and its standard error is the spread of those changes over
  the windows (with snapshots as the unit, two windows picked the test's best
  candidate 8 times in 18 on the storms). With one window there is no such spread: risk stays.

Above :data:`AUTO_MAX_CELLS` candidate cells (the region where the recommended exchange is
skipped too), or with one candidate only (no spatial residual), no validation runs: the choice
is ``"risk"`` (``selection.attrs["skipped"]`` says why). The cost is the time of one refit and
two placements per window (risk + exchange and gp-variance + exchange; the gp-variance greedy
is the latter's start, shared) and one fold-in score per distinct set of cells. The refits are kept
for the next call on the same model and training (another sensor count refits nothing).

The result is an ``xarray.Dataset`` (``plan.refinement["selection"]``): ``mse`` per candidate
and window, ``mse_snapshot`` per held-out snapshot, ``score`` (mean) and ``ucb`` (the guard's
bound) per candidate, the choice and the set-up in its attributes.
"""

from __future__ import annotations

import time
import warnings
from typing import Any

import numpy as np
import xarray as xr

from ..errors import PlanningError
from ..validation.search import BlockGuard, RollingOrigin, search

__all__ = ["AUTO_CANDIDATES", "AUTO_CONFIDENCE", "AUTO_MAX_BLOCK", "AUTO_MAX_CELLS",
           "AUTO_MIN_BLOCK", "AUTO_MIN_FIT", "AUTO_WINDOWS", "auto_unavailable",
           "format_placement_selection", "select_criterion", "validation_windows"]

AUTO_CANDIDATES: dict[str, tuple[str, Any]] = {
    "risk+exchange": ("risk", "auto"),
    "gp-variance+exchange": ("gp-variance", True),
    "gp-variance": ("gp-variance", False),
}
"""Label -> ``(criterion, exchange)``; ``"auto"`` is the recommended exchange rule (skipped
above ``static.EXCHANGE_AUTO_MAX`` candidate cells). The first one wins ties."""
AUTO_MIN_BLOCK: int = 3
"""Fewest snapshots in a held-out block."""
AUTO_MAX_BLOCK: int = 12
"""Most snapshots in a held-out block (a tenth of the training otherwise)."""
AUTO_MIN_FIT: int = 3
"""Fewest snapshots the model is refitted on before a block."""
AUTO_WINDOWS: int = 4
"""Forward windows when the training has room for them (else as many as it has room for)."""
AUTO_CONFIDENCE: float = 1.645
"""Standard errors of the guard: a candidate replaces ``"risk"`` only when the one-sided upper
bound of its MSE change against risk (paired per window, its spread over the windows) is below
0 (the constant of ``select_temporal``'s guard)."""
AUTO_MAX_CELLS: int = 20_000
"""Above this many candidate cells the default is ``"risk"`` without validation (the refits and
kriged scores grow with the cells; the recommended exchange stops here too)."""


def validation_windows(n_snapshots: int, min_fit: int = AUTO_MIN_FIT) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` held-out blocks of the training snapshots (oldest first), each
    with at least ``min_fit`` (>= :data:`AUTO_MIN_FIT`) snapshots before it to refit on;
    PlanningError when there is no room for one."""
    T, min_fit = int(n_snapshots), max(AUTO_MIN_FIT, int(min_fit))
    h = int(min(AUTO_MAX_BLOCK, max(AUTO_MIN_BLOCK, round(T / 10))))
    if T < h + min_fit:
        raise PlanningError(f"criterion='auto' validates on the training snapshots: training "
                            f"has {T}, it needs at least {AUTO_MIN_BLOCK + min_fit} "
                            f"({min_fit} to refit the model, {AUTO_MIN_BLOCK} held out); pass "
                            "more training snapshots or criterion='risk'")
    return RollingOrigin(h, max(1, min(AUTO_WINDOWS, (T - min_fit) // h))).split(T)


def _min_fit(model: Any) -> int:
    """Fewest snapshots a refit before a window needs: more than its parameters per cell."""
    from ..glrm.calibrated import parameters_per_cell

    nk = parameters_per_cell(model)
    return (0 if nk is None else nk[1]) + 2


def auto_unavailable(model: Any, n_snapshots: int) -> str | None:
    """Why ``criterion="auto"`` cannot validate a placement from ``model`` on ``n_snapshots``
    training snapshots (too few for one refit and one held-out block), or None. ``lrm-cvx
    place``, whose ``auto`` is a default, then places by ``"risk"`` with a note."""
    try:
        validation_windows(n_snapshots, min_fit=_min_fit(model))
    except PlanningError as exc:
        return str(exc).split(";")[0]
    return None


def _refit(model: Any, V: np.ndarray, region: Any) -> Any:
    """The model's unfitted copy of every validation (:func:`~lrm_cvx.validation.refits.
    clone_model`: uncalibrated, a chosen rank and kernel kept), memoryless, refitted on
    ``V (t, L)`` on ``region`` (duck typing: any estimator with ``get_params`` and
    ``fit(data, region=)``)."""
    from ..validation.refits import clone_model

    memoryless = {"temporal": None} if "temporal" in model.get_params() else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return clone_model(model, **memoryless).fit(xr.DataArray(V, dims=("time", "cell")),
                                                    region=region)


_REFITS: list[Any] = []
"""The last validation's refits: ``[(key, model ref, region, {window start: (refit,
prior)})]`` (one entry)."""


def _shared_refits(model: Any, region: Any, V: np.ndarray) -> dict[int, tuple[Any, Any]]:
    """The refits of the last validation on the same fitted ``model``, ``region`` and
    training ``V`` (a placement at another sensor count refits the same windows), else a new
    empty table that the next call shares. Keyed on the model object (held weakly), its
    parameters and factors and the training's bytes: a refitted model or other snapshots
    start afresh."""
    import weakref

    from .._validation import array_digest

    key = (array_digest(np.asarray(model.Y_), V), repr(sorted(model.get_params().items())))
    if _REFITS:
        old_key, ref, old_region, table = _REFITS[0]
        if old_key == key and ref() is model and old_region is region:
            return table
    table: dict[int, tuple[Any, Any]] = {}
    try:
        ref = weakref.ref(model)
    except TypeError:  # an estimator that cannot be referenced weakly: no sharing
        return table
    _REFITS[:] = [(key, ref, region, table)]
    return table


def _mse(prior: Any, values: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """``(t,)`` per snapshot the MSE over the cells with a value of the recommended fold-in
    from the sensors' values (their mean is bench_placement.py's score)."""
    from ..belief.posterior import fold_in_maps

    V = np.full(values.shape, np.nan)
    V[:, cells] = values[:, cells]
    pred = fold_in_maps(prior, V)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean((pred - values) ** 2, axis=1)


def select_criterion(model: Any, region: Any, n: int, V: np.ndarray, place: Any,
                     n_allowed: int) -> xr.Dataset:
    """The validation of ``criterion="auto"`` (module docstring): ``V (T, L)`` the training
    snapshots in data units on ``region`` (NaN missing), ``place(refit, training, criterion,
    exchange) -> cells`` one placement of ``n`` sensors from the model refitted on exactly
    ``training`` (the caller's options bound in), ``n_allowed`` the candidate cells. Returns
    the table; ``attrs["choice"]`` is the label of :data:`AUTO_CANDIDATES` that won."""
    t0 = time.perf_counter()
    spatial = getattr(model, "spatial_cov_", None) is not None
    labels = [lab for lab, (crit, _) in AUTO_CANDIDATES.items()
              if crit == "risk" or spatial]
    skipped = ""
    if n_allowed > AUTO_MAX_CELLS:
        skipped = (f"{n_allowed} candidate cells > AUTO_MAX_CELLS = {AUTO_MAX_CELLS}: risk "
                   "without validation")
    elif len(labels) == 1:
        skipped = "the model has no spatial residual: risk (the only candidate)"
    # a refit needs residual degrees of freedom: more snapshots than its k parameters per cell
    windows = [] if skipped else validation_windows(V.shape[0], min_fit=_min_fit(model))
    held_t = np.concatenate([np.arange(a, b) for a, b in windows]) if windows \
        else np.zeros(0, np.int64)

    refits = _shared_refits(model, region, V) if windows else {}

    def window_errors(window: tuple[int, int]) -> dict[str, np.ndarray]:
        """Per held-out snapshot ``(1, b - a)`` the fold-in MSE of each candidate's
        placement from the model refitted on the snapshots before the window (one score per
        distinct set of cells)."""
        a, b = window
        if a not in refits:
            fit = _refit(model, V[:a], region)
            refits[a] = (fit, fit.latent_prior("empirical", spatial=spatial))
        fit, prior = refits[a]
        out, scored = {}, {}
        for lab in labels:
            cells = np.asarray(place(fit, V[:a], *AUTO_CANDIDATES[lab]), dtype=np.int64)
            key = np.sort(cells).tobytes()
            if key not in scored:
                scored[key] = _mse(prior, V[a:b], cells)[None]
            out[lab] = scored[key]
        return out

    stops = np.cumsum([0] + [b - a for a, b in windows])
    rule = BlockGuard(list(zip(stops[:-1], stops[1:], strict=True)), AUTO_CONFIDENCE)
    if windows:
        _, E, decision = search(window_errors, windows, rule)
    else:
        E = np.full((len(labels), 1, 0), np.nan)
        decision = rule(E)
    per, mse, ucb, best = E[:, 0], decision.mse, decision.ucb, decision.choice
    score = mse.mean(axis=1) if windows else np.full(len(labels), np.nan)
    ds = xr.Dataset(
        {"mse": (("candidate", "window"), mse), "score": (("candidate",), score),
         "ucb": (("candidate",), ucb),
         "mse_snapshot": (("candidate", "held"), per)},
        coords={"candidate": labels, "window": np.arange(len(windows)), "held": held_t,
                "window_start": (("window",), np.array([a for a, _ in windows], np.int64)),
                "window_stop": (("window",), np.array([b for _, b in windows], np.int64))})
    ds.attrs.update(choice=labels[best], criterion=AUTO_CANDIDATES[labels[best]][0],
                    exchange=str(AUTO_CANDIDATES[labels[best]][1]), n_sensors=int(n),
                    n_training=int(V.shape[0]), skipped=skipped,
                    seconds=time.perf_counter() - t0,
                    confidence=AUTO_CONFIDENCE,
                    rule="rolling origin on the training snapshots; risk unless a candidate's "
                         "upper confidence bound of its MSE change against risk (paired per "
                         "window, spread over the windows) is below 0; "
                         "then the lowest mean MSE of the recommended fold-in")
    return ds


def format_placement_selection(ds: xr.Dataset) -> str:
    """The validation table as text (the CLI prints it): per candidate its mean validation MSE,
    its MSE in each held-out block (the guard's unit) and its upper bound against risk."""
    if ds.attrs.get("skipped"):
        return f"criterion auto: {ds.attrs['choice']} ({ds.attrs['skipped']})"
    blocks = ", ".join(f"{int(a)}-{int(b) - 1}" for a, b in
                       zip(ds["window_start"].values, ds["window_stop"].values, strict=True))
    lines = [f"criterion auto: {ds.attrs['choice']} (held-out training snapshots {blocks}; "
             "validation MSE of the fold-in: mean [per block])"]
    for lab in ds["candidate"].values:
        mark = "  <- chosen" if lab == ds.attrs["choice"] else ""
        ub = float(ds["ucb"].sel(candidate=lab)) if "ucb" in ds else 0.0
        vs = "" if lab == ds["candidate"].values[0] else f"  (upper bound vs risk {ub:+.1%})"
        per = " ".join(f"{v:.4g}" for v in np.atleast_1d(ds["mse"].sel(candidate=lab).values))
        lines.append(f"  {lab:22s} {float(ds['score'].sel(candidate=lab)):.6g} [{per}]"
                     f"{vs}{mark}")
    return "\n".join(lines)
