"""A temporal model that validates itself: ``GLRM(temporal="auto")``.

Which temporal model maps a record best is an empirical question (monthly sea-surface
temperature gains 40 % from a seasonal model and loses 8 % with a plain AR(1); yearly records have
no season), so :func:`select_temporal` answers it on the user's own training snapshots, the way a
campaign would meet them:

* **Rolling origin.** ``n_folds`` forward-chaining windows of ``n_val`` snapshots end at the last
  training snapshot. For each window the model is refitted on the snapshots *before* it (two
  windows: at most the time of two more fits), and every candidate's dynamics are estimated from
  that refit only. No candidate ever sees the snapshots it is scored on. With a spatial
  residual the refits share one covariance, fitted on the first (earliest) refit's residuals
  with :data:`REFIT_PAIRS` variogram pairs (a variogram fit costs the same at every grid size).
* **Campaign-like designs.** Each validation day is sampled as campaigns sample, the design
  cycling from day to day: a spatially clustered route, a straight transect, scattered cells
  (:func:`~.designs.flown_sets`: drawn among all of the region's cells, so on a day with gaps,
  clouds, some give no value, as in a campaign), one campaign per sample size; the same cells
  for every candidate (paired comparison).
* **The campaign's metric.** The filter runs through the window with each candidate: forecast,
  assimilate the day's samples, predict the whole map; the score is the day's MSE over the
  observed cells not sampled. The candidates' filters run as one batch
  (:func:`~.filter.batch_step`, the algebra of ``LatentFilter.assimilate``).
* **Candidates** (cadence-aware): memoryless (every day's prior the empirical prior), AR(1) and
  the seasonal model (monthly or daily dates seen over two years; yearly data has no season), each
  blended towards the memoryless prior by ``alpha`` (:func:`~.blending.blend_dynamics`):
  ``seasonal`` with ``alpha = 0`` is the seasonal climatology with the anomalies' covariance,
  with ``alpha = 1`` the climatology plus AR(1) anomalies. Each is tried with the residual and
  noise variances inflated by the factors :data:`AUTO_INFLATIONS` (of the one grid
  :data:`~lrm_cvx.glrm.calibrated.RESIDUAL_FACTORS`; ``model.residual_inflation_``,
  label ``"ar1:0.9 x4"``): the fitted variances come from the training residuals of a basis
  fitted to those very snapshots, which under-state a new snapshot's, so the latent update
  from a few clustered samples is over-confident and spreads a local anomaly over the whole
  map. An inflation trusts the latent update less and leaves the local part to the kriged
  residual (its kriging weights do not change); a day's maps under every candidate still come
  from one batch of filters.
* **Rule, with a guard on harm.** A candidate is admissible when the upper confidence bound of
  its day-by-day MSE change against memoryless (one-sided at the normal level of
  ``confidence`` standard errors, a paired bootstrap over the days:
  :func:`~.paired.bootstrap_upper`) is at most ``tolerance`` at every size; memoryless
  always is. The admissible candidate with the lowest worst MSE ratio (over sizes) is the
  validated best (``attrs["best"]``). **One standard error towards caution:** among the
  candidates of the best's kind and blend whose day-by-day MSE is within one standard error of
  the best's at every size (paired, the one-standard-error rule of cross-validation), the
  choice is the lowest rank (``rank="auto"``) and then the largest inflation, so validation
  days that cannot tell two candidates apart leave the model with fewer modes and the update
  that trusts a few samples less. A campaign's robot samples around its base day after day,
  and an over-confident update from the same few cells compounds there, which the
  validation's designs (a new place every day) do not show.

The result is an ``xarray.Dataset`` (``model.selection_``, saved with the model by
``modelfile.validation_tables``): the validation table per candidate and size and the choice
in its attributes.
"""

from __future__ import annotations

import copy
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import xarray as xr

from .._blas import single_threaded_blas
from .._validation import as_generator, check_ranks
from ..errors import DataError, ModelError
from ..glrm.calibrated import RESIDUAL_FACTORS
from ..glrm.dynamics import kind_dynamics
from .paired import AUTO_DESIGNS, AUTO_SIZES, MAX_SCORED
from .search import (
    HeldOutCells,
    OneStandardError,
    PairedGuard,
    RollingOrigin,
    search,
    selection_table,
)

__all__ = ["select_temporal", "AutoUnavailable", "AUTO_ALPHAS",
           "AUTO_DESIGNS", "AUTO_SIZES", "AUTO_INFLATIONS", "AUTO_RANKS", "REFERENCE_RANK",
           "memoryless_twin", "MIN_AUTO_SNAPSHOTS", "MAX_SCORED", "REFIT_PAIRS",
           "apply_selection", "auto_unavailable", "check_auto_data", "format_selection"]

AUTO_ALPHAS = (0.0, 0.5, 0.9, 1.0)
"""Blends towards the memoryless prior tried for every temporal kind."""
AUTO_INFLATIONS = RESIDUAL_FACTORS[2::2]
"""Factors of the residual and noise variances tried with every temporal candidate: the whole
doublings from 1 of the one grid :data:`~lrm_cvx.glrm.calibrated.RESIDUAL_FACTORS` (1, 2, 4, 8;
each costs a filter per day and candidate)."""
AUTO_RANKS = (3, 5, 8, 12)
"""Ranks ``GLRM(rank="auto")`` validates (jointly with the temporal candidates)."""
REFERENCE_RANK = 5
"""The rank the rule's reference (memoryless) candidate has under ``rank="auto"``: the
default rank, which another must beat with confidence."""
MIN_AUTO_SNAPSHOTS = 8
"""Fewest training snapshots ``temporal="auto"`` validates on (3 to refit, 2 windows)."""
REFIT_PAIRS = 50_000
"""Pairs of the refits' residual variogram (a fit's: 200,000; the candidates share it)."""
_MIN_REGULAR = 0.8  # share of the steps that must be one median step


def _candidate_label(kind: str, alpha: float, inflation: float = 1.0,
                     rank: int | None = None) -> str:
    base = "none" if kind == "none" else f"{kind}:{alpha:g}"
    base = base if inflation == 1.0 else f"{base} x{inflation:g}"
    return base if rank is None else f"rank {rank} {base}"


def check_auto_data(data: Any) -> None:
    """The early check of ``GLRM(temporal="auto").fit(data)``: a ``(time, lat, lon)``
    DataArray with at least :data:`MIN_AUTO_SNAPSHOTS` snapshots (DataError / ModelError)."""
    if not isinstance(data, xr.DataArray) or data.ndim != 3:
        raise DataError("temporal='auto' needs (time, lat, lon) DataArray data (its sample "
                        "designs are routes and transects on the grid)")
    if data.shape[0] < MIN_AUTO_SNAPSHOTS:
        raise ModelError(f"temporal='auto' needs at least {MIN_AUTO_SNAPSHOTS} snapshots to "
                         f"validate a choice, got {data.shape[0]}; pass temporal=None or 'ar1'")


def auto_unavailable(data: Any) -> str | None:
    """Why ``temporal="auto"`` cannot run on ``data``, found before any fit (too few snapshots,
    no, unsorted or irregular time coordinate: the checks of :func:`select_temporal`), or None.
    ``lrm-cvx fit`` falls back to no dynamics on it when auto is only its default."""
    from ..errors import LrmError
    from ..glrm.dynamics import check_times

    try:
        check_auto_data(data)
        tdim = data.dims[0]
        if tdim not in data.coords:
            raise ModelError(f"temporal='auto' needs a time coordinate on the data's {tdim!r} "
                             "dim")
        check_times(data[tdim], f"data[{tdim!r}]")
        _check_regular(data[tdim], f"data[{tdim!r}]")
    except LrmError as exc:
        return str(exc)
    return None


def _check_regular(times: Any, name: str) -> None:
    """ModelError unless most steps of ``times`` are one median step (dynamics need a step)."""
    from ..glrm.dynamics import time_numbers

    t = time_numbers(times, name)[0]
    d = np.diff(t)
    step = float(np.median(d))
    regular = np.isclose(d / step, 1.0, rtol=0.15)  # months of 28-31 days are one step
    if np.mean(regular) < _MIN_REGULAR:
        raise ModelError(
            f"temporal='auto' needs regularly spaced snapshots: only {int(regular.sum())} of "
            f"{d.size} steps of {name} are the median step ({step:g}); use temporal=None, or "
            f"resample the record to a regular step")


def _window_errors(sub: Any, dynamics: list[Any], V: np.ndarray, times: np.ndarray,
                   region: Any, sizes: Sequence[int], designs: Sequence[str],
                   rng: np.random.Generator, spatial: bool | None,
                   inflation: Any = None) -> np.ndarray:
    """Day MSE ``(n_candidates, n_sizes, n_days)`` of the filter with each of ``dynamics``
    (None: memoryless) and residual ``inflation`` (default 1) through the snapshots
    ``V (n_days, L)`` at ``times``.

    One campaign per size; day ``i`` is sampled by design ``designs[i % len(designs)]`` (a
    campaign's routes change from day to day). The candidates share each day's sample cells,
    so their filters run as one batch (``filter.batch_step``: the algebra of
    ``LatentFilter.assimilate``, the observations' GLS terms computed once) and the kriged
    residual maps of all of them come from one kriging call (its weights depend on the cells
    only)."""
    from ..belief.filter import batch_start, batch_step, batch_transitions

    n, holdout = V.shape[0], HeldOutCells(MAX_SCORED)
    err = np.full((len(dynamics), len(sizes), n), np.nan)
    first = batch_start(sub, dynamics, spatial=spatial, inflation=inflation)
    steps = [batch_transitions(first.dynamics, t0, t1)  # the same for every size
             for t0, t1 in zip([first.time, *times[:-1]], times, strict=True)]
    for s_i, size in enumerate(sizes):
        batch = first
        for i, t in enumerate(times):
            # the design's cells (gaps: NaN) and an unbiased sample of the map's error
            cells, h = holdout.split(region, np.isfinite(V[i]), size,
                                     designs[i % len(designs)], rng)
            batch = batch_step(batch, steps[i], cells, V[i, cells], t)
            if h.size:
                means = _map_means(batch.mean, batch.obs, cells, V[i, cells], h)
                err[:, s_i, i] = np.mean((means - V[i, h]) ** 2, axis=1)
    return err


def _map_means(means: np.ndarray, obs: Any, cells: np.ndarray, values: np.ndarray,
               targets: np.ndarray) -> np.ndarray:
    """Posterior mean maps ``(n_cand, len(targets))`` in data units of the latent means
    ``(n_cand, k)`` of beliefs that share their observations ``values`` at ``cells``: the trend
    ``Y^T m`` plus, with a spatial residual, the residuals at the observations kriged with one
    set of weights (universal kriging given each GLS mean)."""
    M = means.T  # (k, n_cand)
    mu = obs.Y[:, targets].T @ M  # (|targets|, n_cand)
    if obs.is_spatial:
        from .. import spatial as sp
        from ..belief.posterior import average_repeats

        keep = ~np.isnan(values)
        uc, zc = average_repeats(cells[keep], obs.to_fit_units(cells[keep], values[keep]))
        if uc.size:
            cov = obs.spatial_cov
            res = zc[:, None] - obs.Y[:, uc].T @ M  # (n_obs, n_cand)
            meth = "direct" if uc.size <= sp.MAX_DIRECT else "neighbors"
            r_mu, _ = sp.krige_core(cov, cov.points(obs.region, uc), res,
                                    cov.points(obs.region, targets), method=meth,
                                    neighbors=32, cutoff=1e-6, want_var=False)
            mu = mu + r_mu.T
    out = obs.to_data_units(mu.T, None, targets)[0]
    return np.asarray(out)


def select_temporal(model: Any, data: Any, *, kinds: Sequence[str] = ("ar1", "seasonal"),
                    alphas: Sequence[float] = AUTO_ALPHAS,
                    inflations: Sequence[float] = AUTO_INFLATIONS, n_val: int | None = None,
                    n_folds: int = 2, sizes: Sequence[int] = AUTO_SIZES,
                    designs: Sequence[str] = AUTO_DESIGNS, confidence: float = 1.645,
                    tolerance: float = 0.01, spatial: bool | None = None, seed: Any = 0,
                    values: np.ndarray | None = None,
                    ranks: Sequence[int] | None = None) -> xr.Dataset:
    """Choose the temporal model of ``model`` by rolling-origin validation on ``data``.

    ``model``: a GLRM fitted on ``data`` ``(time, lat, lon)``, its training snapshots (only
    they are read). ``kinds``: the temporal kinds tried beside memoryless, each with the blends
    ``alphas``; a kind the record cannot carry (a season on yearly data, or fewer than two years
    before the first window) is skipped and named in ``attrs["skipped"]``. ``inflations``:
    factors (>= 1) of the residual and noise variances tried with every candidate (1, the
    model as fitted, always). ``n_val``: days per
    window (default a fifth of the record, between 3 and 24). ``spatial``: krige the residual in
    the validation maps (None: when the model has a spatial residual, as campaigns do; the
    kriged residual and the forecast interact, so the choice is scored on the maps users get).
    Each day's map is scored on at most :data:`MAX_SCORED` random unsampled cells.
    ``values``: ``data`` already stacked by the model's region ``(T, L)`` (``GLRM.fit`` hands
    over its own; None: stacked here). On a region of more than
    ``refits.VALIDATION_MAX_CELLS`` cells the refits, designs and scores read one window of it
    (:func:`~lrm_cvx.validation.refits.validation_view`). See the module docstring for the rule.

    ``ranks`` (``GLRM(rank="auto")``): also choose the rank among these. Every window is
    refitted at each rank and every candidate tried at each (labels ``"rank 8 seasonal:1
    x2"``), all on the same sample cells; the reference is memoryless at
    :data:`REFERENCE_RANK` (or the middle rank offered). A rank the earliest window's
    history cannot carry (more than half its snapshots) is skipped. ``kinds=()`` validates the
    rank alone (memoryless candidates).

    Returns a Dataset over ``candidate`` (coordinates ``kind``, ``alpha``, ``inflation``) and
    ``size``: ``mse`` (mean validation-day MSE), ``ratio`` (to memoryless as fitted), ``ucb``
    (the bound of the rule), ``admissible``; attributes ``choice`` (a candidate label,
    ``"none"`` for memoryless), ``choice_kind``, ``choice_alpha``, ``choice_inflation``,
    ``best`` (the lowest worst ratio, before the one-standard-error step),
    ``n_days``, ``designs``, ``skipped`` (and with ``ranks`` a ``rank`` coordinate and
    ``choice_rank``).
    """
    from ..glrm.dynamics import TEMPORAL, check_times
    from .refits import clone_model, refit_carries, training_values, validation_view

    model, data, values = validation_view(model, data, values)  # a large region: a window
    # one stacking pass, float32 as region.stack gives it (the scoring promotes the values
    # exactly; the refits read it as a (time, cell) DataArray, not gathered again)
    if values is None:
        region, V = training_values(model, data, dtype=np.float32)
    else:
        region, V = model.region_, np.asarray(values).astype(np.float32, copy=False)
        if V.shape != (data.shape[0], model.n_cells_):
            raise DataError(f"values must be data stacked to ({data.shape[0]}, "
                            f"{model.n_cells_}), got shape {V.shape}")
    V.setflags(write=False)  # a refit must not zero-fill it in place
    T = V.shape[0]
    if T < MIN_AUTO_SNAPSHOTS:
        raise ModelError(f"temporal='auto' needs at least {MIN_AUTO_SNAPSHOTS} training "
                         f"snapshots to validate a choice, got {T}; pass temporal=None or "
                         f"'ar1'")
    tdim = data.dims[0]
    if tdim not in data.coords:
        raise ModelError(f"temporal='auto' needs a time coordinate on the data's {tdim!r} dim")
    check_times(data[tdim], f"data[{tdim!r}]")
    _check_regular(data[tdim], f"data[{tdim!r}]")
    kinds = [TEMPORAL.canonical(k, "kinds") for k in kinds]
    if any(k in ("none", "auto") for k in kinds):
        raise ModelError(f"kinds must name temporal models ('ar1', 'seasonal'), got {kinds}")
    alphas = sorted({float(a) for a in alphas})
    if not alphas or min(alphas) < 0 or max(alphas) > 1:
        raise ModelError(f"alphas must be blends in [0, 1], got {alphas}")
    inflations = sorted({1.0, *(float(r) for r in inflations)})
    if not all(np.isfinite(r) and r >= 1.0 for r in inflations):
        raise ModelError(f"inflations must be finite factors >= 1, got {inflations}")
    # a sample set must leave most of the map to score: sizes up to half the observed cells
    n_obs = float(np.median(np.isfinite(V).sum(axis=1)))
    sizes = [int(s) for s in sizes if int(s) <= n_obs / 2] or [max(1, int(n_obs / 4))]
    n_val = min(24, max(3, T // 5)) if n_val is None else int(n_val)
    if not 2 <= n_val <= T - 3:
        raise ModelError(f"n_val must be in [2, {T - 3}] for {T} snapshots, got {n_val}")
    n_folds = max(1, min(int(n_folds), (T - 3) // n_val))
    carries = None
    if ranks is None:  # the earliest refit must carry the model's rank (a short record)
        rank, offset = int(model.rank_), getattr(model, "offset_", None) is not None

        def carries(lo: int) -> bool:  # a refit on the snapshots before lo
            return lo >= 1 and refit_carries(np.isfinite(V[:lo]), rank, offset)

    windows = RollingOrigin(n_val, n_folds).split(T, carries)
    if windows is None:
        raise AutoUnavailable(f"temporal='auto' cannot validate on {T} snapshots: a refit of "
                              f"the model's rank on the snapshots before a validation window "
                              f"(at most {T - 2}) would leave no residual degrees of freedom; "
                              "pass temporal=None or 'ar1', or a lower rank")
    rng = as_generator(seed)
    # the earliest window's history
    rank_list, skipped_ranks = _check_ranks(ranks, windows[0][0], int(model.n_cells_))
    ranked = rank_list != [None]  # then every rank's candidates meet the same days' cells
    all_times = data[tdim].values
    meta: dict[str, tuple[str, float, float, int | None]] = {}
    skipped: set[str] = set(skipped_ranks)
    family = getattr(clone_model(model), "spatial", None)  # a spatial="auto" model's choice
    shared = [None]  # the first refit's residual covariance, shared by the later refits

    def score(window: tuple[int, int]) -> dict[str, np.ndarray]:
        """Day errors ``(size, day)`` per candidate label on one window."""
        lo, end = window
        window_seed = int(rng.integers(2**62)) if ranked else 0
        out: dict[str, np.ndarray] = {}
        for rank in rank_list:
            sub, shared[0] = _refit_before(model, V, lo, all_times, tdim, region, rank,
                                           family, shared[0])
            models = _candidate_models(sub, kinds, alphas, all_times[:lo], skipped)
            labels, dyns, infl = [], [], []
            for r in inflations:  # the memoryless model as fitted first: the rule's reference
                for kind, a, dyn in models:
                    labels.append(_candidate_label(kind, a, r, rank))
                    meta[labels[-1]] = (kind, a, r, rank)
                    dyns.append(dyn)
                    infl.append(r)
            with single_threaded_blas():  # k x k and n x n algebra: threads only add waiting
                E = _window_errors(sub, dyns, V[lo:end], all_times[lo:end], region, sizes,
                                   designs, np.random.default_rng(window_seed) if ranked
                                   else rng, spatial, infl)
            out.update(zip(labels, E, strict=True))
        return out

    labels, E, decision = search(score, windows, _temporal_rule(meta, confidence, tolerance),
                                 drop=lambda lab: meta[lab][0] in skipped)
    return _table(decision, labels, meta, sizes, designs, confidence, tolerance, skipped,
                  ranked)


def _refit_before(model: Any, V: np.ndarray, lo: int, times: np.ndarray, tdim: str,
                  region: Any, rank: int | None, family: Any, shared_cov: Any
                  ) -> tuple[Any, Any]:
    """``(sub, shared_cov)``: ``model`` refitted (AR(1), no spatial fit, ``rank`` when given)
    on the snapshots ``V[:lo]`` before a window, given the residual covariance shared by every
    refit (fitted here on the first refit's residuals when there is none yet)."""
    from ..glrm.predictive import residual_covariance
    from .refits import clone_model

    over = {} if rank is None else {"rank": int(rank)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        before = xr.DataArray(V[:lo], dims=(tdim, "cell"), coords={tdim: times[:lo]})
        sub = clone_model(model, temporal="ar1", spatial=None, **over).fit(before,
                                                                           region=region)
        if family is not None:  # fitted once, on the earliest refit's snapshots only
            if shared_cov is None:
                shared_cov = residual_covariance(sub, V[:lo], family, max_pairs=REFIT_PAIRS)
            sub.spatial, sub.spatial_cov_ = family, shared_cov
    sub.calibration_ = None
    return sub, shared_cov


def _candidate_models(sub: Any, kinds: Sequence[str], alphas: Sequence[float],
                      times: np.ndarray, skipped: set[str]) -> list[tuple[str, float, Any]]:
    """``[(kind, alpha, dynamics)]`` of a refit ``sub`` (its snapshots at ``times``):
    memoryless first, then each kind of ``kinds`` blended by each of ``alphas``; a kind the
    history cannot carry is added to ``skipped`` (and not tried again)."""
    from .blending import blend_dynamics, memoryless_cov

    models: list[tuple[str, float, Any]] = [("none", 0.0, None)]
    for kind in kinds:
        base = None if kind in skipped else kind_dynamics(kind, sub, times)
        if base is None:
            skipped.add(kind)
            continue
        S = memoryless_cov(sub, base)
        models += [(kind, a, blend_dynamics(base, a, S)) for a in alphas
                   if not (kind == "ar1" and a == 0.0)]  # ar1:0 is memoryless itself
    return models


class AutoUnavailable(ModelError):
    """``temporal="auto"`` cannot validate on these training snapshots (too short a record
    for a refit of the model's rank before any validation window). ``lrm-cvx fit``, whose
    ``auto`` is a default, then fits without dynamics and says so."""


def _check_ranks(ranks: Sequence[int] | None, history: int, n_cells: int
                 ) -> tuple[list[int | None], list[str]]:
    """The ranks :func:`select_temporal` refits at, reference first (``[None]``: the model's
    own), and the labels of those skipped (more than half the earliest window's ``history``
    snapshots, or not below the cell count)."""
    if ranks is None:
        return [None], []
    asked = sorted(check_ranks(ranks))
    ok = [r for r in asked if 2 * r <= history and r < n_cells]
    if not ok:
        raise ModelError(f"rank='auto': none of the ranks {asked} can be refitted on the "
                         f"earliest validation window's {history} snapshots (at most half of "
                         "them); pass an integer rank")
    ref = REFERENCE_RANK if REFERENCE_RANK in ok else ok[(len(ok) - 1) // 2]
    return [ref] + [r for r in ok if r != ref], [f"rank {r}" for r in asked if r not in ok]


def _temporal_rule(meta: dict, confidence: float, tolerance: float) -> OneStandardError:
    """The rule of :func:`select_temporal`: the paired guard against memoryless (candidate
    0), then one standard error towards caution among the best's kind and blend: the lowest
    rank (``rank="auto"``; fewer modes to estimate from a few samples), then the largest
    inflation (an update that trusts a few samples less)."""
    def caution(lab: str) -> tuple:  # larger is more cautious
        _, _, inflation, *rank = meta[lab]
        return (-rank[0] if rank and rank[0] is not None else 0, inflation)

    return OneStandardError(PairedGuard(confidence, tolerance, "temporal='auto'"),
                            group=lambda lab: tuple(meta[lab][:2]), caution=caution)


def _rule(E: np.ndarray, labels: list[str], meta: dict, sizes: list[int],
          designs: Sequence[str], confidence: float, tolerance: float,
          skipped: set[str], ranked: bool = False) -> xr.Dataset:
    """The table of :func:`select_temporal` from the day errors ``E (n_candidates, n_sizes,
    n_days)`` (candidate 0 is memoryless) under its rule."""
    decision = _temporal_rule(meta, confidence, tolerance)(E, labels)
    return _table(decision, labels, meta, sizes, designs, confidence, tolerance, skipped,
                  ranked)


def _table(decision: Any, labels: list[str], meta: dict, sizes: list[int],
           designs: Sequence[str], confidence: float, tolerance: float, skipped: set[str],
           ranked: bool) -> xr.Dataset:
    """The validation table of :func:`select_temporal` (the search's, with the candidates'
    kind, blend and inflation, and their rank with ``ranked``)."""
    kind, alpha, inflation, *rank = meta[labels[decision.choice]]  # (..., rank) with ranks
    coords = {name: ("candidate", [meta[lab][i] for lab in labels])
              for i, name in enumerate(("kind", "alpha", "inflation"))}
    ds = selection_table(
        decision, labels, sizes, reference="the memoryless model", coords=coords,
        what="mean validation-day MSE of the map (held-out cells)", choice_kind=kind,
        choice_alpha=float(alpha), choice_inflation=float(inflation),
        best=labels[decision.best], n_days=int(decision.n_cases), designs=",".join(designs),
        skipped=",".join(sorted(skipped)), confidence=float(confidence),
        tolerance=float(tolerance))
    if ranked:
        ds = ds.assign_coords(rank=("candidate", [int(meta[lab][3]) for lab in labels]))
        ds.attrs["choice_rank"] = int(rank[0])
    return ds


def apply_selection(model: Any, selection: xr.Dataset) -> None:
    """Set ``model.dynamics_`` to the chosen candidate, estimated on all of ``model``'s
    snapshots (blended by the chosen ``alpha``; None for memoryless), its
    ``residual_inflation_`` and ``selection_``."""
    from .blending import blend_dynamics, memoryless_cov

    kind = selection.attrs["choice_kind"]
    model.selection_ = selection
    model.residual_inflation_ = float(selection.attrs.get("choice_inflation", 1.0))
    if kind == "none":
        model.dynamics_ = None
        return
    xa = model.X_
    times = xa[xa.dims[1]] if hasattr(xa, "dims") else np.arange(model._Xv.shape[1])
    base = kind_dynamics(kind, model, times)
    if base is None:  # the full record carries what its first window carried
        raise ModelError(f"temporal='auto' chose {kind!r} but it cannot be estimated on all "
                         f"snapshots")
    model.dynamics_ = blend_dynamics(base, float(selection.attrs["choice_alpha"]),
                                     memoryless_cov(model, base))


def memoryless_twin(model: Any) -> Any:
    """``model`` as ``temporal=None`` fits it: a shallow copy whose ``residual_inflation_`` (a
    part of ``temporal="auto"``'s choice) is 1; ``model`` itself when it already is. The
    reference the choice is validated against, and ``evaluate``'s memoryless twin."""
    if float(getattr(model, "residual_inflation_", 1.0)) == 1.0:
        return model
    twin = copy.copy(model)
    twin.residual_inflation_ = 1.0
    return twin


def _rows_shown(selection: xr.Dataset) -> list[int]:
    """Rows of the printed table: every candidate, or with ranks (``rank="auto"``: up to a
    hundred) the reference, the choice and each rank's best (lowest worst ratio), in table
    order."""
    if "rank" not in selection.coords:
        return list(range(selection.sizes["candidate"]))
    worst = selection["ratio"].max("size").values
    ranks = selection["rank"].values
    keep = {0, list(selection["candidate"].values).index(selection.attrs["choice"])}
    for r in np.unique(ranks):
        idx = np.flatnonzero(ranks == r)
        keep.add(int(idx[np.argmin(worst[idx])]))
    return sorted(keep)


def format_selection(selection: xr.Dataset, short: bool = False) -> str:
    """The validation table as text (the CLI prints it); ``short``: one line (the demo's)."""
    if short:
        choice = selection.attrs["choice"]
        worst = float(selection["ratio"].sel(candidate=choice).max())
        return (f"temporal='auto' chose {choice!r} (MSE x{worst:.2f} of memoryless over "
                f"{selection.attrs['n_days']} validation days)")
    sizes = [int(s) for s in selection["size"].values]
    labels = [str(lab) for lab in selection["candidate"].values]
    rows = _rows_shown(selection)
    width = max(18, 2 + max(len(labels[i]) for i in rows))
    head = f"{'candidate':<{width}}" + "".join(f"{'MSE@' + str(s):>12}" for s in sizes)
    lines = [f"temporal='auto' chose {selection.attrs['choice']!r} (rolling origin, "
             f"{selection.attrs['n_days']} validation days, designs "
             f"{selection.attrs['designs']})", head + f"{'worst ratio':>13}  admissible"]
    for i in rows:
        mse = selection["mse"].values[i]
        worst = float(selection["ratio"].values[i].max())
        ok = "yes" if bool(selection["admissible"].values[i]) else "no"
        mark = " *" if labels[i] == selection.attrs["choice"] else ""
        lines.append(f"{labels[i]:<{width}}" + "".join(f"{v:12.4g}" for v in mse)
                     + f"{worst:13.3f}  {ok}{mark}")
    if len(rows) < len(labels):
        lines.append(f"(the reference, the choice and each rank's best of {len(labels)} "
                     "candidates; all in model.selection_)")
    if selection.attrs.get("skipped"):
        lines.append(f"skipped (the record cannot carry them): {selection.attrs['skipped']}")
    best = selection.attrs.get("best", selection.attrs["choice"])
    if best != selection.attrs["choice"]:
        lines.append(f"the lowest worst ratio is {best!r}; {selection.attrs['choice']!r} is "
                     "within one standard error of it and more cautious (a lower rank or a "
                     "larger inflation)")
    if "inflation" in selection.coords and float(selection["inflation"].max()) > 1.0:
        lines.append("'xN': residual and noise variances N times the fitted ones")
    return "\n".join(lines)
