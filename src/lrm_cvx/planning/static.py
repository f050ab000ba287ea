"""Static sensor placement (no travel): :func:`place_sensors`, its greedy on the information
criteria, and on the fold-in's own error the ``"risk"`` criterion and the exchange search
(docs/planning.md "Static placement").

**Risk.** The recommended fold-in (``complete(prior=..., spatial=...)``) predicts a snapshot
from sensors ``S`` by Gaussian conditioning: with ``C0`` the prior covariance of the latent
field (``Y^T S0 Y``, plus the GP residual ``sill rho(d)`` with the spatial residual), ``N`` the
observation noise (the nugget, or the per-cell noise variance) and ``m`` the prior mean,
``pred = m + C0[:, S] (C0[S, S] + N_S)^-1 (z_S - m_S)`` (fit units; the data units scale the
error at cell ``i`` by ``scale_i``). The risk of ``S`` is that predictor's squared error over
the **training** snapshots, ``J(S) = sum_t sum_i w_i (z_ti - pred_ti)^2`` (``w = scale^2``:
data units; cells missing in a training snapshot count as residual 0, i.e. the prior mean).
Adding a cell ``x`` is one exact rank-one conditioning step: with ``C`` the posterior
covariance given ``S``, ``Z`` the current errors (``T x L``) and ``d = C_xx + N_x``,
``Z' = Z - Z[:, x] C[x, :] / d`` and ``C' = C - C[:, x] C[x, :] / d``, so the decrease of ``J``
is ``2 u.P_x / d - |u|^2 cc_x / d^2`` (``u = Z[:, x]``, ``P = Z W C``, ``cc_x = C[:, x]^T W
C[:, x]``). ``P`` and ``cc`` are kept up to date by the same rank-one algebra, so each pick is
``O(L^2 + T L)`` (one matrix-vector product and one rank-one update of ``C``).

**Exchange.** From a placement, each sensor in turn is removed (an exact rank-one
*un*-conditioning: ``C_R = C_S + v v^T / M_ss``, ``v = C0[:, S] M[:, s]``,
``M = (C0[S, S] + N_S)^-1``) and replaced by the cell with the largest gain if that gain beats
putting the sensor back by more than ``1e-9`` of the objective; sweeps repeat until a sweep
changes nothing (a local optimum: no single swap improves) or ``sweeps`` is reached. The
objective never increases. The state is rebuilt from scratch at the start of every sweep
(no drift). Available for ``"risk"`` and ``"gp-variance"`` (total posterior variance).

**Memory and cost.** The state above is the dense reference (``method="dense"``): the
``L x L`` posterior covariance (``8 L^2`` bytes: 16 MB at 1,421 cells, 3.2 GB at 20,000) plus
``O(T L)``, built in row blocks; set-up ``O(L^2 (T + k))``, each pick ``O(L^2 + T L)``, each
exchange sweep ``O(n L^2)`` plus a rebuild. Regions above :data:`RISK_MAX_CELLS` cells raise
:class:`PlanningError`. The default (``method="auto"``) runs the same greedy and exchange in the
scalable form of :mod:`lrm_cvx.planning.static_risk` (no ``L x L`` matrix, ``O((n + T) p)`` per
step for ``p`` candidate cells, FFT sums of the stationary residual; the same picks), unless the
residual's metric is km.

**Default.** ``place_sensors(model, n, training=...)`` with no other option is
``criterion="auto"`` (:mod:`~lrm_cvx.planning.static_auto`): ``"risk"`` + the exchange,
``"gp-variance"`` + the exchange or the ``"gp-variance"`` greedy, whichever validates best on
the training snapshots (rolling origin; ``"risk"`` without validation above
``AUTO_MAX_CELLS`` candidate cells). ``"risk"``'s recommended exchange is skipped above
:data:`EXCHANGE_AUTO_MAX` candidate cells; an explicit ``exchange=`` without a criterion
keeps ``"risk"``. ``paper=True`` is the paper's Fisher greedy; ``place_sensors(Y, region,
n)`` keeps the Fisher default (no prior to take a risk from), and with ``prior=`` and
``training=`` it is ``"risk"`` + the exchange.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import scipy.linalg
from tqdm.auto import tqdm

from .._validation import as_factor_matrix, check_flag
from ..errors import DataError, ModelError, PlanningError, RegionError
from ..information import CRITERION_REGISTRY, fisher_information, make_oracle
from ..recommended import recommended_criterion
from ..region import Region
from .plan import Plan, check_region
from .request import PlanPath
from .terms import PRIOR_TERMS, PriorTerms, history_arrays, oracle_terms, resolve_prior, split_prior

__all__ = ["EXCHANGE_AUTO_MAX", "RISK_MAX_CELLS", "STATIC_CRITERIA", "place_sensors",
           "place_static", "risk_objective", "stack_training", "training_residuals",
           "error_factor", "fitted_on"]

RISK_MAX_CELLS: int = 20_000
"""Largest region (cells) of the dense risk / exchange state (``8 L^2`` bytes: 3.2 GB)."""

STATIC_CRITERIA: tuple[str, ...] = ("risk", "auto")
"""Criteria of :func:`~lrm_cvx.planning.place_sensors` beyond the planning criteria registry
(static placement only: they need training snapshots)."""

EXCHANGE_SWEEPS: int = 5
EXCHANGE_AUTO_MAX: int = 20_000
"""The recommended default runs the exchange after the greedy up to this many candidate cells
(above, the greedy alone: the exchange costs ~``3 x sweeps`` greedies)."""
_REL_TOL = 1e-9  # a swap must lower the objective by more than this fraction
_BLOCK = 1024  # rows per block of the L x L updates (bounds the temporaries)


# --------------------------------------------------------------------------- the fold-in's prior
class _FoldIn:
    """The fold-in's Gaussian process on the region's cells (fit units).

    ``block(rows)`` -> ``C0[rows, :]`` ``(len(rows), L)``; ``noise (L,)``; ``w (L,)`` the
    error weights (``scale^2``, ones without a scale); ``mean (L,)`` the prior mean of the
    latent value (``Y^T m0``; None for the gp-variance terms, which have no mean)."""

    def __init__(self, Y: np.ndarray, S0: np.ndarray, region: Region, spatial_cov: Any,
                 noise: np.ndarray, w: np.ndarray, mean: np.ndarray | None) -> None:
        self.Y, self.S0, self.region, self.spatial_cov = Y, 0.5 * (S0 + S0.T), region, spatial_cov
        self.noise, self.w, self.mean = noise, w, mean
        self.L = Y.shape[1]
        self._all = np.arange(self.L)

    def block(self, rows: np.ndarray) -> np.ndarray:
        if self.spatial_cov is None:
            return self.Y[:, rows].T @ self.S0 @ self.Y
        from ..information import gp_latent_cov

        return gp_latent_cov(self.Y, self.S0, self.region, self.spatial_cov, rows, self._all)

    def cols(self, cells: np.ndarray) -> np.ndarray:
        """``C0[:, cells]`` ``(L, n)`` (symmetric: the rows' block transposed)."""
        return self.block(np.asarray(cells, dtype=np.int64)).T


def _fold_in_from_prior(prior: Any, Yk: np.ndarray, region: Region) -> tuple[_FoldIn, Any]:
    """``(fold-in, observation model)`` of ``prior`` (a :class:`LatentPosterior` or a fitted
    GLRM) for the risk."""
    from ..belief.posterior import LatentPosterior

    if prior is None:
        raise PlanningError("criterion='risk' needs prior=: the fold-in's belief "
                            "(model.latent_prior('empirical', spatial=True)) or the fitted GLRM")
    if not isinstance(prior, LatentPosterior):
        if hasattr(prior, "latent_prior") and hasattr(prior, "Y_"):
            try:
                prior = prior.latent_prior("empirical",
                                           spatial=getattr(prior, "spatial_cov_", None) is not None)
            except ModelError as exc:
                raise PlanningError(f"prior: {exc}") from None
        else:
            raise PlanningError("prior must be a LatentPosterior (model.latent_prior("
                                f"'empirical', spatial=True)) or a fitted GLRM, got "
                                f"{type(prior).__name__}")
    if prior.cells.size:
        raise PlanningError("prior has observations assimilated already; pass the belief "
                            "before any observation (model.latent_prior(...))")
    if not prior.is_proper:
        raise PlanningError("criterion='risk' needs a proper prior (prior='empirical'), not a "
                            "flat one: the fold-in of a few sensors must be defined")
    obs = prior.obs_model
    if obs.Y.shape != Yk.shape or not np.allclose(obs.Y, Yk, rtol=1e-6, atol=1e-12):
        raise PlanningError(f"Y {Yk.shape} is not the prior's factor matrix {obs.Y.shape}: "
                            "pass the model's Y_ with its latent_prior")
    L = Yk.shape[1]
    if obs.is_spatial:
        from ..information import gp_noise

        if obs.region is not None and obs.region.n_cells != region.n_cells:
            raise PlanningError("region is not the prior's region")
        noise = np.full(L, gp_noise(obs.spatial_cov))
    else:
        noise = np.asarray(obs.noise_at(np.arange(L)), dtype=np.float64)
    w = np.ones(L) if obs.scale is None else np.asarray(obs.scale, np.float64) ** 2
    return _FoldIn(Yk, np.asarray(prior.cov, np.float64), region, obs.spatial_cov, noise, w,
                   Yk.T @ np.asarray(prior.mean, np.float64)), obs


def training_residuals(training: Any, region: Region, obs: Any, mean: np.ndarray,
                       model: Any = None) -> np.ndarray:
    """``(T, L)`` training snapshots in fit units minus the fold-in's prior mean (a missing
    value: 0, the prior mean, unless ``model`` is given, below). ``training``: a ``(time,
    lat, lon)`` DataArray on the region's grid, a ``(time, cell)`` DataArray, or a ``(T, L)``
    / ``(T, ny, nx)`` array.

    ``model``: the fitted GLRM whose fold-in this is, **fitted on exactly these snapshots**
    (:func:`fitted_on` tells). Each error is then made a new snapshot's: the fitted part
    ``Y^T x_t - mean`` is kept and the fit's residual is scaled by :func:`error_factor`; a
    missing value is the fitted part alone (the snapshot's latent state is known from its
    other cells, its residual there is not). Without ``model`` a gap under a cloud would read
    as the mean: a sensor there would seem to measure the mean on that day."""
    V = stack_training(training, region)
    Z = obs.to_fit_units(np.arange(region.n_cells), V) - mean[None, :]
    seen = np.isfinite(Z)
    if model is None:
        Z[~seen] = 0.0
        return Z
    c = error_factor(model)
    X = np.asarray(model.X_, np.float64)
    Y = np.asarray(obs.Y, np.float64)
    for t in range(0, Z.shape[0], 32):  # Z = fitted + c (Z - fitted), in blocks (no 2nd T x L)
        F = X[:, t:t + 32].T @ Y - mean
        Zb = Z[t:t + 32]
        Zb *= c
        Zb += (1.0 - c) * F
        gap = ~seen[t:t + 32]
        Zb[gap] = F[gap]
    return Z


def error_factor(model: Any) -> float:
    """``n / (n - k)``: how much larger a new snapshot's residual is than the model's residual
    on its own training snapshots (std).

    Each cell's ``k`` parameters (rank, plus the offset) were fitted to its ``n`` training
    snapshots, so their residuals hold only ``(n - k) / n`` of the residual variance, while a
    new snapshot's residual holds ``n / (n - k)`` of it: its own plus the parameters' error
    (``glrm.calibrated.prediction_factor``, which the fold-in's covariance already carries).
    Scaling the training residuals by ``sqrt(residual_dof * prediction_factor)`` makes the
    risk score a placement on the errors it will meet, not on errors the fit has already
    absorbed (1.02 at rank 5 on 300 snapshots, 1.12 on 55, 1.25 on 30)."""
    from ..glrm.calibrated import prediction_factor, residual_dof

    return float(np.sqrt(residual_dof(model) * prediction_factor(model)))


def fitted_on(model: Any, training: Any) -> bool:
    """Whether ``training`` holds exactly the snapshots ``model`` was fitted on: the same
    times as its ``X_``. A model fitted on a plain array, or ``training`` given as an array,
    cannot tell: False (the errors are taken as given)."""
    X = getattr(model, "X_", None)
    if not _is_model(model) or not hasattr(X, "dims") or not hasattr(training, "dims"):
        return False
    tdim = X.dims[-1]
    return bool(tdim in training.dims and training.sizes[tdim] == X.sizes[tdim]
                and np.array_equal(np.asarray(training[tdim].values),
                                   np.asarray(X[tdim].values)))


def stack_training(training: Any, region: Region) -> np.ndarray:
    """``(T, L)`` float64 training snapshots in data units on the region's cells (NaN missing),
    from the forms :func:`training_residuals` takes; PlanningError naming ``training``."""
    if training is None:
        raise PlanningError("criterion='risk' needs training=: the training snapshots, a "
                            "(time, lat, lon) DataArray on the region's grid")
    if hasattr(training, "latent_prior") and hasattr(training, "Y_"):
        raise PlanningError("training must be the training snapshots (a (time, lat, lon) "
                            "DataArray); a fitted GLRM does not keep its data: pass it as prior=")
    try:
        if hasattr(training, "dims"):
            V = region.stack(training)
        else:
            V = np.asarray(training)
            if V.ndim == 3:
                V = region.stack(V)
            elif V.ndim != 2 or V.shape[1] != region.n_cells:
                raise RegionError(f"an array must be (T, {region.n_cells}) or (T, ny, nx), "
                                  f"got shape {V.shape}")
    except (RegionError, DataError, ValueError, TypeError) as exc:
        raise PlanningError(f"training is not on the region's grid: {exc}") from None
    V = np.asarray(V, dtype=np.float64)
    if V.ndim == 1:
        V = V[None, :]
    if V.ndim != 2 or V.shape[0] < 1:
        raise PlanningError(f"training must hold snapshots (time, cells), got shape {V.shape}")
    if np.isinf(V).any():
        raise PlanningError("training values must be finite (NaN marks a missing value)")
    if not np.isfinite(V).any():
        raise PlanningError("training has no finite value")
    return V


# --------------------------------------------------------------------------- the dense state
class _State:
    """Posterior covariance ``C (L, L)`` given ``cells`` and, for the risk, the training errors
    ``Z (T, L)`` with ``P = Z W C`` and ``cc = diag(C W C)``; ``R`` the prior errors."""

    def __init__(self, gp: _FoldIn, R: np.ndarray | None, cells: list[int]) -> None:
        self.gp, self.R = gp, R
        self.rebuild(cells)

    def rebuild(self, cells: list[int]) -> None:
        gp, L = self.gp, self.gp.L
        self.C = self.P = None  # free the old state first: one L x L matrix at a time
        C = np.empty((L, L))
        for a in range(0, L, _BLOCK):
            C[a:a + _BLOCK] = gp.block(np.arange(a, min(a + _BLOCK, L)))
        C = 0.5 * (C + C.T) if L <= _BLOCK else C
        S = np.asarray(cells, dtype=np.int64)
        Z = None if self.R is None else self.R.copy()
        if S.size:
            A = C[np.ix_(S, S)] + np.diag(gp.noise[S])
            Lc = np.linalg.cholesky(0.5 * (A + A.T))
            B = scipy.linalg.solve_triangular(Lc, C[S, :], lower=True)  # (n, L)
            if Z is not None:
                Z -= scipy.linalg.solve_triangular(Lc, self.R[:, S].T, lower=True).T @ B
            for a in range(0, L, _BLOCK):
                C[a:a + _BLOCK] -= B[:, a:a + _BLOCK].T @ B
        self.C, self.Z, self.cells = C, Z, [int(c) for c in S]
        w = gp.w
        self.cc = np.zeros(L)
        for a in range(0, L, _BLOCK):
            self.cc += w[a:a + _BLOCK] @ (C[a:a + _BLOCK] ** 2)
        self.P = None if Z is None else (Z * w) @ C

    @property
    def value(self) -> float:
        """The objective: training squared error (risk) or total posterior variance."""
        w = self.gp.w
        if self.Z is None:
            return float(w @ np.diag(self.C))
        return float(w @ np.einsum("ti,ti->i", self.Z, self.Z))

    def gains(self) -> np.ndarray:
        """``(L,)`` decrease of the objective from adding each cell (exact)."""
        d = np.diag(self.C) + self.gp.noise
        if self.Z is None:
            return self.cc / d
        cross = np.einsum("ti,ti->i", self.Z, self.P)
        zz = np.einsum("ti,ti->i", self.Z, self.Z)
        return 2.0 * cross / d - zz * self.cc / d ** 2

    def _rank_one(self, alpha: float, a: np.ndarray, b: np.ndarray | None) -> None:
        """``C += alpha a a^T``, ``Z += alpha b a^T``, with ``P`` and ``cc`` kept exact."""
        w = self.gp.w
        q = self.C @ (w * a)  # C W a
        aw = float(a @ (w * a))
        self.cc += 2.0 * alpha * a * q + alpha ** 2 * aw * a * a
        if self.Z is not None:
            zwa = self.Z @ (w * a)  # Z W a
            self.P += alpha * (np.outer(zwa, a) + np.outer(b, q)) \
                + alpha ** 2 * aw * np.outer(b, a)
            self.Z += alpha * np.outer(b, a)
        L = a.size
        for s in range(0, L, _BLOCK):
            self.C[s:s + _BLOCK] += alpha * np.outer(a[s:s + _BLOCK], a)

    def add(self, x: int) -> None:
        """Condition on a sensor at ``x``."""
        a = self.C[:, x].copy()
        d = float(a[x] + self.gp.noise[x])
        b = None if self.Z is None else self.Z[:, x].copy()
        self._rank_one(-1.0 / d, a, b)
        self.cells.append(int(x))

    def remove(self, x: int) -> None:
        """Forget the sensor at ``x`` (exact un-conditioning from ``M = (C0[S,S] + N)^-1``)."""
        S = np.asarray(self.cells, dtype=np.int64)
        j = int(np.flatnonzero(S == x)[0])
        G = self.gp.cols(S)  # (L, n)
        A = G[S] + np.diag(self.gp.noise[S])
        m = scipy.linalg.solve(0.5 * (A + A.T), np.eye(S.size)[:, j], assume_a="pos")
        v = G @ m
        b = None if self.Z is None else self.R[:, S] @ m
        self._rank_one(1.0 / float(m[j]), v, b)
        self.cells.pop(j)


# --------------------------------------------------------------------------- algorithms
def _greedy(state: _State, n: int, allowed: np.ndarray, hist: dict[str, list]) -> None:
    active = np.zeros(state.gp.L, dtype=bool)
    active[allowed] = True
    active[state.cells] = False
    while len(state.cells) < n:
        g = np.where(active, state.gains(), -np.inf)
        x = int(np.argmax(g))  # ties: the lowest cell
        if not np.isfinite(g[x]):
            break
        state.add(x)
        active[x] = False
        for key, v in (("cell", x), ("gain", g[x]), ("cost_increase", 1.0), ("ratio", g[x]),
                       ("cost", float(len(state.cells))), ("n_evaluated", int(active.sum()) + 1),
                       ("objective", state.value)):
            hist[key].append(v)


def _exchange(state: _State, allowed: np.ndarray, sweeps: int) -> dict[str, Any]:
    """Swap sensors while a swap lowers the objective (see the module docstring)."""
    t0 = time.perf_counter()
    start = list(state.cells)
    state.rebuild(start)
    before = state.value
    moves: dict[str, list] = {"exchange_out": [], "exchange_in": [], "exchange_gain": []}
    done, n_sweeps = False, 0
    for n_sweeps in range(1, sweeps + 1):
        if n_sweeps > 1:
            state.rebuild(state.cells)  # from scratch: no drift of the rank-one updates
        changed = False
        for i in range(len(state.cells)):
            s = state.cells[i]
            state.remove(s)
            g = state.gains()
            ok = np.zeros(g.size, dtype=bool)
            ok[allowed] = True
            ok[state.cells] = False
            g = np.where(ok, g, -np.inf)
            x = int(np.argmax(g))
            tol = _REL_TOL * max(abs(state.value), 1e-300)
            if x != s and g[x] > g[s] + tol:
                state.add(x)
                moves["exchange_out"].append(s)
                moves["exchange_in"].append(x)
                moves["exchange_gain"].append(float(g[x] - g[s]))
                changed = True
            else:
                state.add(s)
            state.cells.insert(i, state.cells.pop())  # keep the sensor's slot
        if not changed:
            done = True
            break
    from .static_risk import finish_exchange

    return finish_exchange(state, state.cells, start, before, moves, n_sweeps, done, t0)


def _check_size(L: int, what: str) -> None:
    if L > RISK_MAX_CELLS:
        raise PlanningError(
            f"{what} holds the dense L x L posterior covariance; the region has {L} cells > "
            f"RISK_MAX_CELLS = {RISK_MAX_CELLS} ({8 * L * L / 1e9:.1f} GB): use "
            "criterion='gp-variance' without exchange (scales to millions of cells), or a "
            "coarser region")


def _check_sweeps(sweeps: Any) -> int:
    if isinstance(sweeps, (bool, np.bool_)) or not isinstance(sweeps, (int, np.integer)) \
            or sweeps < 1:
        raise PlanningError(f"sweeps must be an integer >= 1, got {sweeps!r}")
    return int(sweeps)


def risk_objective(prior: Any, training: Any, cells: Any, region: Region | None = None) -> float:
    """``J(cells)``: the fold-in's squared error over the training snapshots (data units,
    summed over snapshots and cells; missing training values as :func:`training_residuals`
    fills them), from scratch. ``prior``: a LatentPosterior or a fitted GLRM; a GLRM fitted on
    exactly ``training`` (:func:`fitted_on`) scores a new snapshot's errors
    (:func:`error_factor`), as the placement does."""
    from ..belief.posterior import LatentPosterior

    if not isinstance(prior, LatentPosterior) and hasattr(prior, "latent_prior"):
        region = prior.region_ if region is None else region
    elif region is None:
        region = prior.obs_model.region
    region = check_region(region)
    Y = (prior.obs_model.Y if isinstance(prior, LatentPosterior) else prior.Y)
    gp, obs = _fold_in_from_prior(prior, np.asarray(Y, np.float64), region)
    R = training_residuals(training, region, obs, gp.mean,
                           model=prior if fitted_on(prior, training) else None)
    S = np.asarray(cells, dtype=np.int64)
    if S.size == 0:
        return float(gp.w @ np.einsum("ti,ti->i", R, R))
    G = gp.cols(S)
    A = G[S] + np.diag(gp.noise[S])
    Z = R - R[:, S] @ np.linalg.solve(A, G.T)
    return float(gp.w @ np.einsum("ti,ti->i", Z, Z))


def _state(gp: _FoldIn, R: np.ndarray | None, cells: list[int], allowed: np.ndarray,
           method: str, max_candidates: int, what: str, n: int) -> Any:
    """The dense ``_State`` or the scalable ``FactoredState`` (``method``: "auto" picks the
    scalable one unless the residual's metric is "km", which it cannot take)."""
    from . import static_risk as sr

    km = gp.spatial_cov is not None and getattr(gp.spatial_cov, "metric", "grid") != "grid"
    if method == "factored" and km:
        raise PlanningError("method='factored' needs the residual's metric 'grid' (FFT sums); "
                            "use method='dense' for metric='km'")
    if method == "dense" or km:
        _check_size(gp.L, what)
        return _State(gp, R, cells)
    pool = sr.candidate_pool(gp.region, allowed, max_candidates)
    if pool.size < n:
        raise PlanningError(f"max_candidates = {max_candidates} thins the {allowed.size} "
                            f"allowed cells to {pool.size} < n_sensors = {n}: raise it")
    if cells:
        pool = np.union1d(pool, np.asarray(cells, dtype=np.int64))
    state = sr.FactoredState(gp.Y, gp.S0, gp.spatial_cov, gp.noise, gp.w, R, pool, gp.region)
    for c in cells:
        state.add(int(np.searchsorted(pool, c)))
    return state


def place_static(
    Y: Any,
    region: Region,
    n: int,
    allowed: np.ndarray,
    *,
    criterion: str,
    prior: Any = None,
    training: Any = None,
    exchange: bool = False,
    sweeps: int = EXCHANGE_SWEEPS,
    method: str = "auto",
    max_candidates: int | None = None,
    other: dict[str, Any] | None = None,
    in_sample: bool = False,
) -> Plan:
    """``criterion="risk"`` (greedy on the training error, then optionally the exchange), or
    the exchange after the registry criterion's greedy (``"gp-variance"`` only). Called by
    :func:`~lrm_cvx.planning.place_sensors` with ``n`` and ``allowed`` (the candidate cells)
    validated; ``other`` holds its remaining keyword arguments (passed on for gp-variance).
    ``method``: ``"auto"`` (the scalable form of ``planning/static_risk.py`` unless the
    residual's metric is km), ``"factored"`` or ``"dense"`` (the ``L x L`` reference).
    ``in_sample=True``: ``prior`` is the GLRM fitted on exactly ``training`` (the caller knows:
    the validation's refits), so the risk takes a new snapshot's errors (:func:`error_factor`);
    otherwise that is told from the times (:func:`fitted_on`)."""
    from . import static_risk as sr

    region = check_region(region)
    Yk = as_factor_matrix(Y, region)
    L = Yk.shape[1]
    other = dict(other or {})
    sweeps = _check_sweeps(sweeps)
    if method not in ("auto", "factored", "dense"):
        raise PlanningError(f"method must be 'auto', 'factored' or 'dense', got {method!r}")
    if max_candidates is None:
        max_candidates = sr.MAX_CANDIDATES
    if isinstance(max_candidates, (bool, np.bool_)) or not isinstance(
            max_candidates, (int, np.integer)) or max_candidates < n:
        raise PlanningError(f"max_candidates must be an integer >= n_sensors = {n}, got "
                            f"{max_candidates!r}")
    auto = isinstance(exchange, str) and exchange == "auto"
    if auto:  # the recommended default: the exchange where the candidate count allows
        exchange = allowed.size <= EXCHANGE_AUTO_MAX
        skipped = (f"{allowed.size} candidate cells > EXCHANGE_AUTO_MAX = "
                   f"{EXCHANGE_AUTO_MAX}: greedy only (pass exchange=True)")
    if not isinstance(exchange, (bool, np.bool_)):
        raise PlanningError(f"exchange must be True or False, got {exchange!r}")
    if isinstance(criterion, str) and criterion == "risk":
        given = sorted(key for key, v in other.items()
                       if v is not None and not (key in ("ridge",) and float(v) == 0.0)
                       and key not in ("progress", "traversable"))
        if given:
            raise PlanningError(f"criterion='risk' takes its terms from prior= and training=; "
                                f"{given} do not apply")
        gp, obs = _fold_in_from_prior(prior, Yk, region)
        model = prior if in_sample or fitted_on(prior, training) else None
        R = training_residuals(training, region, obs, gp.mean, model=model)
        factor = 1.0 if model is None else error_factor(model)
        state = _state(gp, R, [], allowed, method, int(max_candidates), "criterion='risk'",
                       n)
        hist: dict[str, list] = {k: [] for k in ("cell", "gain", "cost_increase", "ratio",
                                                 "cost", "n_evaluated", "objective")}
        if isinstance(state, _State):
            _greedy(state, n, allowed, hist)
        else:
            sr.greedy(state, n, hist)
        crit, posterior = "risk", True
    else:
        if training is not None:
            raise PlanningError("training= is for criterion='risk' only")
        crit = CRITERION_REGISTRY.canonical(criterion, "criterion")
        if crit != "gp-variance":
            raise PlanningError(f"exchange=True is available for criterion 'risk' and "
                                f"'gp-variance', not {crit!r}")
        if other.get("targets") is not None:
            raise PlanningError("exchange=True with gp-variance sums the variance over every "
                                "cell: targets= does not apply")
        terms = resolve_prior(prior, {k: other.get(k) for k in (
            "prior_precision", "noise_var", "target_weights", "prior_cov", "spatial_cov")})
        from ..information import check_gp_inputs, gp_noise

        S0 = check_gp_inputs(Yk, region, terms["spatial_cov"], terms["prior_cov"])
        tw = terms["target_weights"]
        gp = _FoldIn(Yk, S0, region, terms["spatial_cov"],
                     np.full(L, gp_noise(terms["spatial_cov"])),
                     np.ones(L) if tw is None else np.asarray(tw, np.float64), None)
        if method == "dense" or getattr(terms["spatial_cov"], "metric", "grid") != "grid":
            # the registry's greedy, then the dense state for the exchange
            rest = {k: v for k, v in other.items() if k not in PRIOR_TERMS}
            given = {k: other[k] for k in PRIOR_TERMS if other.get(k) is not None}
            base = place_sensors(Yk, region, n, criterion=crit, exchange=False, prior=(
                PriorTerms(**given) if prior is None and given else prior), **rest)
            state = _state(gp, None, [int(c) for c in base.cells], allowed, method,
                           int(max_candidates), "exchange=True", n)
            hist = {k: list(v) for k, v in base.history.items()}
            hist["objective"] = []  # the gp greedy's own value per pick is not recorded
            posterior = bool(base.posterior)
        else:  # the same greedy (same gains) on the scalable state: no registry oracle
            state = _state(gp, None, [], allowed, method, int(max_candidates),
                           "criterion='gp-variance'", n)
            hist = {k: [] for k in ("cell", "gain", "cost_increase", "ratio", "cost",
                                    "n_evaluated", "objective")}
            sr.greedy(state, n, hist)
            posterior = terms["prior_precision"] is not None or terms["noise_var"] is not None
    info: dict[str, Any] = {}
    if exchange and state.cells:
        info = (_exchange(state, allowed, sweeps) if isinstance(state, _State)
                else sr.exchange(state, sweeps, _REL_TOL))
    info["form"] = "dense" if isinstance(state, _State) else "factored"
    if crit == "risk":  # the in-sample residuals' scale (1: the errors as given)
        info["training_error_factor"] = factor
    if auto and not exchange:
        info["exchange_skipped"] = skipped
    if not isinstance(state, _State):
        info["n_candidates"] = int(state.pool.size)
    cells = list(state.cells)
    hist_out = {key: np.asarray(v, dtype=np.int64 if key in ("cell", "n_evaluated",
                                                            "exchange_out", "exchange_in")
                                else np.float64)
                for key, v in {**hist, **info.pop("moves", {})}.items() if key != "objective"
                or len(v)}
    plan = Plan.build(
        region=region, cells=cells, route=cells, cost=float(len(cells)),
        information=fisher_information(Yk, cells, 0.0) if cells else -np.inf,
        criterion=crit, budget=float(n), start=-1, ridge=float(other.get("ridge") or 0.0),
        method="greedy+exchange"
        if exchange else "greedy", history=hist_out, cost_function="sensors", Y=Yk,
        posterior=posterior, route_cost=np.arange(1, len(cells) + 1, dtype=np.float64),
        path=PlanPath(kind="static", unit="sensors", budgets=[float(n)],
                      traversable="none" if allowed.size == L else "mask"),
    )
    plan.refinement.update(info)
    plan.refinement["objective"] = state.value
    return plan


def _qr_start(Yk: np.ndarray, allowed: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` cells of a column-pivoted QR of ``Y[:, allowed]`` (QR-DEIM / PySensors' QR
    placement): a well-conditioned set of ``k`` cells, so the information is nonsingular."""
    from scipy.linalg import qr

    _, _, piv = qr(Yk[:, allowed], mode="economic", pivoting=True)
    return allowed[piv[:k]].astype(np.int64)


def _is_model(obj: Any) -> bool:
    return hasattr(obj, "latent_prior") and hasattr(obj, "Y_")


def _resolve_call(Y: Any, region: Any, n_sensors: Any, prior: Any) -> tuple[Any, Any, Any,
                                                                             Any, bool]:
    """``(Y, region, n, prior, from_model)`` of the two call forms ``(model, n)`` /
    ``(model, region, n)`` and ``(Y, region, n)``."""
    if not _is_model(Y):
        if n_sensors is None:
            raise PlanningError("place_sensors(Y, region, n_sensors): n_sensors is missing "
                                "(or pass a fitted GLRM: place_sensors(model, n))")
        return Y, region, n_sensors, prior, False
    model = Y
    if n_sensors is None and not isinstance(region, Region):
        region, n_sensors = None, region
    if n_sensors is None:
        raise PlanningError("place_sensors(model, n_sensors): n_sensors is missing")
    if getattr(model, "Y_", None) is None:
        raise PlanningError("place_sensors(model, ...): the model is not fitted")
    if region is None:
        region = getattr(model, "region_", None)
        if region is None:
            raise PlanningError("place_sensors(model, ...): the model has no region (fitted on "
                                "an array): pass region= or fit it on a (time, lat, lon) "
                                "DataArray")
    return model.Y_, region, n_sensors, model if prior is None else prior, True


def _recommended(from_model: bool, prior: Any, training: Any, paper: bool, criterion: Any,
                 exchange: Any) -> tuple[str, bool]:
    """``(criterion, exchange)`` of the call: the given ones, the paper's (``paper=True``:
    Fisher, no exchange) or the recommended default (docs/planning.md "Static placement")."""
    if paper:
        if criterion not in (None, "fisher") or exchange:
            raise PlanningError("paper=True is the paper's Fisher greedy: criterion and "
                                "exchange do not apply")
        if training is not None:
            raise PlanningError("paper=True is the paper's Fisher greedy: training= does not "
                                "apply")
        return "fisher", False
    if isinstance(criterion, str) and criterion == "auto":
        if exchange is not None:
            raise PlanningError("criterion='auto' chooses the exchange too: leave exchange "
                                "unset, or pass criterion='risk' / 'gp-variance'")
        if training is None:
            raise PlanningError("criterion='auto' validates on training=: pass the training "
                                "snapshots (a (time, lat, lon) DataArray on the model's grid)")
        if prior is None:
            raise PlanningError("criterion='auto' refits the model: pass a fitted GLRM "
                                "(place_sensors(model, n, training=...))")
        return "auto", None
    if criterion is not None:
        return criterion, bool(exchange) if exchange is not None else False
    if training is not None:  # the fold-in's own training error, then the exchange
        if prior is None:
            raise PlanningError("training= (the recommended criterion 'risk') needs the "
                                "fold-in's belief: pass a fitted GLRM first, or prior=")
        if from_model and exchange is None:  # the criterion validated on the training
            return "auto", None
        return "risk", "auto" if exchange is None else bool(exchange)
    spatial = from_model and getattr(_model_of(prior), "spatial_cov_", None) is not None
    criterion = recommended_criterion(spatial) if from_model else "fisher"
    return criterion, bool(exchange) if exchange is not None else False


def _model_of(prior: Any) -> Any:
    return prior if _is_model(prior) else None


def place_sensors(
    Y: Any,
    region: Any = None,
    n_sensors: Any = None,
    *,
    criterion: str | None = None,
    ridge: float = 0.0,
    prior: Any = None,
    progress: bool = False,
    traversable: Any = None,
    training: Any = None,
    exchange: bool | None = None,
    sweeps: int = 5,
    paper: bool = False,
    method: str = "auto",
    max_candidates: int | None = None,
) -> Plan:
    """Static placement: ``n_sensors`` fixed sensors (moorings, stations), no travel.

    Two call forms:

    * ``place_sensors(model, n, training=snapshots)`` with a fitted GLRM (its ``Y_``,
      ``region_`` and empirical prior with the spatial residual). **The default is the
      recommended placement**: with ``training`` (the training snapshots, a ``(time, lat,
      lon)`` DataArray on the model's grid) ``criterion="auto"``: ``"risk"`` + exchange,
      ``"gp-variance"`` + exchange or ``"gp-variance"``, chosen by rolling-origin validation
      on ``training`` (planning/static_auto.py; the table is ``plan.refinement["selection"]``);
      with ``exchange=`` given, ``"risk"``; without ``training``, ``"gp-variance"`` for a model
      with a spatial residual, else ``"fisher"``.
    * ``place_sensors(Y, region, n)`` with a factor matrix: no prior, so the default stays the
      paper's ``"fisher"`` (the risk and gp-variance need the fold-in's prior covariance and
      residual, which only a fitted model or ``prior=`` gives); with ``prior=`` and
      ``training=`` it is the recommended ``"risk"`` + exchange.

    ``paper=True`` (or ``criterion="fisher"``) is the paper's Fisher greedy, unchanged.

    The greedy of :func:`~lrm_cvx.planning.plan_greedy` with every sensor costing 1: candidates
    are all valid cells (or the cells of a boolean ``(lat, lon)`` DataArray ``traversable``:
    where a sensor may stand), and each step adds the cell of largest gain (ties to the lowest
    cell) until ``n_sensors`` are placed (or no cell gains anything). The criteria and ``prior``
    (a belief or a :class:`~lrm_cvx.planning.terms.PriorTerms`) are those of :func:`plan_greedy`.

    Initial cells: none when the information is nonsingular from the start (``ridge > 0``, a
    prior precision, or ``"gp-variance"``); else (Fisher with ``ridge=0`` and no prior) the
    first ``k`` pivots of a column-pivoted QR of ``Y`` (the QR placement of PySensors), and
    ``n_sensors`` must be ``>= k``. Returns a :class:`Plan` with ``path["kind"] == "static"``,
    ``route`` = the sensors in selection order (no travel), ``route_cost`` = the number of
    sensors placed so far, ``cost`` = the number of sensors, ``start = -1``.

    ``criterion="risk"``: the greedy on the fold-in's own squared reconstruction error over
    the ``training`` snapshots; ``prior`` is the fold-in's belief
    (``model.latent_prior("empirical", spatial=True)``) or the fitted GLRM. It places exactly
    ``n_sensors``. ``exchange=True`` (``"risk"`` or ``"gp-variance"``) then swaps sensors while
    a swap lowers the objective (at most ``sweeps`` sweeps; never worse). ``method="auto"``
    runs both in the scalable form (``planning/static_risk.py``: no ``L x L`` matrix, exact,
    candidates thinned to a sub-lattice above ``max_candidates`` cells) unless the residual's
    metric is km; ``"dense"`` is the ``L x L`` reference (at most ``RISK_MAX_CELLS`` cells).
    """
    paper = check_flag(paper, "paper", error=PlanningError)
    prior, terms = split_prior(prior)
    Y, region, n_sensors, prior, from_model = _resolve_call(Y, region, n_sensors, prior)
    criterion, exchange = _recommended(from_model, prior, training, paper, criterion, exchange)
    auto = isinstance(criterion, str) and criterion == "auto"
    if from_model and _is_model(prior) and criterion not in ("risk", "fisher", "auto"):
        prior = prior.latent_prior("empirical",
                                   spatial=getattr(prior, "spatial_cov_", None) is not None)
    elif from_model and _is_model(prior) and criterion == "fisher":
        prior = None  # the paper's Fisher greedy: no prior
    region = check_region(region)
    Yk = as_factor_matrix(Y, region)
    k, L = Yk.shape
    if isinstance(n_sensors, (bool, np.bool_)) or n_sensors is None:
        raise PlanningError(f"n_sensors must be an integer >= 1, got {n_sensors!r}")
    try:
        n = int(n_sensors)
        ok = n == float(n_sensors) and n >= 1
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise PlanningError(f"n_sensors must be an integer >= 1, got {n_sensors!r}")
    risk = isinstance(criterion, str) and criterion == "risk"
    if not risk and not auto:
        criterion = CRITERION_REGISTRY.canonical(criterion, "criterion")
    if traversable is None or (isinstance(traversable, str) and traversable == "valid"):
        allowed = np.arange(L, dtype=np.int64)
    else:
        mask = _site_mask(region, traversable)
        gi = region.grid_index
        allowed = np.flatnonzero(mask[gi[:, 0], gi[:, 1]]).astype(np.int64)
        if allowed.size == 0:
            raise PlanningError("traversable allows no valid cell for a sensor")
    if n > allowed.size:
        raise PlanningError(f"n_sensors = {n} but only {allowed.size} cells can hold a sensor")
    if auto:
        return _place_auto(Yk, region, n, allowed, prior, training, dict(
            sweeps=sweeps, method=method, max_candidates=max_candidates, other=dict(
                ridge=ridge, progress=progress, traversable=traversable, **terms)))
    if risk or exchange is not False or training is not None:
        return place_static(Yk, region, n, allowed, criterion=criterion, prior=prior,
                            training=training, exchange=exchange, sweeps=sweeps,
                            method=method, max_candidates=max_candidates, other=dict(
                                ridge=ridge, progress=progress, traversable=traversable,
                                **terms))
    targets = terms.pop("targets")
    terms = resolve_prior(prior, terms)
    posterior = terms["prior_precision"] is not None or terms["noise_var"] is not None
    extra = oracle_terms(criterion, region, allowed, terms, targets)
    P0 = np.empty(0, dtype=np.int64)
    try:
        oracle = make_oracle(criterion, Yk, ridge, P0, **extra)
    except PlanningError as exc:
        if criterion != "fisher" or "singular" not in str(exc):
            raise
        if n < k:
            raise PlanningError(
                f"n_sensors = {n} < rank k = {k}: with ridge=0 and no prior the information "
                f"of fewer than {k} sensors is singular; pass ridge > 0 or a prior") from None
        P0 = _qr_start(Yk, allowed, k)
        oracle = make_oracle(criterion, Yk, ridge, P0, **extra)
    cells = [int(c) for c in P0]
    active = np.ones(allowed.size, dtype=bool)
    active[np.searchsorted(allowed, P0)] = False
    hist: dict[str, list[float]] = {
        "cell": [], "gain": [], "cost_increase": [], "ratio": [], "cost": [], "n_evaluated": []
    }
    bar = tqdm(desc="sensor placement", unit="sensor", disable=not progress, leave=False)
    try:
        while len(cells) < n:
            gains = np.where(active, oracle.gains(allowed), -np.inf)
            b = int(np.argmax(gains))
            if not gains[b] > 0:
                break
            cell = int(allowed[b])
            active[b] = False
            oracle.add(cell)
            cells.append(cell)
            for key, v in (("cell", cell), ("gain", gains[b]), ("cost_increase", 1.0),
                           ("ratio", gains[b]), ("cost", float(len(cells))),
                           ("n_evaluated", int(active.sum()) + 1)):
                hist[key].append(v)
            bar.update(1)
    finally:
        bar.close()
    route_cost = np.arange(1, len(cells) + 1, dtype=np.float64)
    plan = Plan.build(
        region=region, cells=cells, route=cells, cost=float(len(cells)),
        information=fisher_information(Yk, cells, ridge), criterion=criterion,
        budget=float(n), start=-1, ridge=float(ridge), method="greedy",
        history=history_arrays(hist), cost_function="sensors", Y=Yk, posterior=posterior,
        route_cost=route_cost,
        path=PlanPath(kind="static", unit="sensors", budgets=[float(n)],
                      traversable="none" if allowed.size == L else "mask"),
    )
    plan._terms = extra  # the criterion's terms, which plan.certify() bounds
    return plan


def _place_auto(Yk: np.ndarray, region: Region, n: int, allowed: np.ndarray, prior: Any,
                training: Any, options: dict[str, Any]) -> Plan:
    """``criterion="auto"``: the criterion chosen on the training snapshots
    (:mod:`~lrm_cvx.planning.static_auto`), run on the full model and training; the validation
    table is ``plan.refinement["selection"]``."""
    from .static_auto import AUTO_CANDIDATES, AUTO_MAX_CELLS, select_criterion

    other = options["other"]
    given = sorted(key for key, v in other.items()
                   if v is not None and not (key == "ridge" and float(v) == 0.0)
                   and key not in ("progress", "traversable"))
    if given:
        raise PlanningError(f"criterion='auto' takes its terms from the model and training=; "
                            f"{given} do not apply")
    V = stack_training(training, region)
    model = _model_of(prior)
    if model is None and allowed.size <= AUTO_MAX_CELLS:
        raise PlanningError("criterion='auto' refits the model on the earlier training "
                            "snapshots: pass the fitted GLRM (place_sensors(model, n, "
                            "training=...) or prior=model), not a LatentPosterior")

    greedy: dict[int, tuple[Any, np.ndarray]] = {}  # id(refit) -> (refit, gp greedy's cells)

    def place(fit: Any, Vtr: np.ndarray, crit: str, exchange: Any) -> np.ndarray:
        risk = crit == "risk"  # the refit's own training: a new snapshot's errors
        if crit == "gp-variance" and exchange is False and id(fit) in greedy:
            return greedy[id(fit)][1]  # the exchange's start on this refit: the same greedy
        plan = place_static(np.asarray(fit.Y_, np.float64), region, n, allowed,
                            criterion=crit, exchange=exchange, in_sample=risk,
                            prior=fit if risk else fit.latent_prior("empirical", spatial=True),
                            training=Vtr if risk else None,
                            sweeps=options["sweeps"], method=options["method"],
                            max_candidates=options["max_candidates"],
                            other={**other, "progress": False})
        if crit == "gp-variance" and exchange is True:
            greedy.clear()  # one refit at a time: the windows run one after another
            greedy[id(fit)] = (fit, np.asarray(plan.history["cell"], dtype=np.int64))
        return plan.cells

    ds = select_criterion(model, region, n, V, place, int(allowed.size))
    crit, exchange = AUTO_CANDIDATES[ds.attrs["choice"]]
    if crit != "risk" and _is_model(prior):
        prior = prior.latent_prior("empirical", spatial=True)
    plan = place_static(Yk, region, n, allowed, criterion=crit, prior=prior,
                        training=training if crit == "risk" else None, exchange=exchange,
                        sweeps=options["sweeps"], method=options["method"],
                        max_candidates=options["max_candidates"], other=other)
    plan.refinement["selection"] = ds
    return plan


def _site_mask(region: Region, traversable: Any) -> np.ndarray:
    """``traversable`` as a ``(ny, nx)`` bool array on the region's grid (a DataArray must
    have the region's lat/lon), else a PlanningError naming it."""
    arr = np.asarray(getattr(traversable, "values", traversable))
    bad = arr.shape != tuple(region.shape) or arr.dtype != bool
    if not bad and hasattr(traversable, "dims"):
        from ..region import spatial_dims

        try:
            la, lo = spatial_dims(traversable)
            bad = not (np.allclose(traversable[la].values, region.lat.values)
                       and np.allclose(traversable[lo].values, region.lon.values))
        except Exception:
            bad = True
    if bad:
        raise PlanningError(f"traversable must be None, 'valid' or a boolean (lat, lon) "
                            f"DataArray on the region's grid {tuple(region.shape)}, got "
                            f"{type(traversable).__name__} of shape {arr.shape}")
    return arr
