"""The :class:`GLRM` estimator: fit on snapshots, complete new snapshots, save and load.

xarray lives here at the edge; the numerical work is in :mod:`.fit` and :mod:`.foldin`.
"""

from __future__ import annotations

import inspect
import json
import os
import warnings
from collections.abc import Mapping
from typing import Any

import numpy as np
import xarray as xr

from .._validation import as_generator, atomic_output, check_positive
from ..errors import DataError, ModelError, NotFittedError
from ..recommended import RECOMMENDED
from ..region import Region
from . import kernels as K
from .dynamics import TEMPORAL, Dynamics, error_rows, foldin_covs, temporal_value
from .dynamics import estimate as estimate_dynamics
from .fit import DataStats, FitResult, check_data, fit_glrm
from .hooks import HOOKS
from .losses import get_loss
from .modelfile import (
    MODEL_FORMAT,
    MODEL_FORMAT_VERSION,
    params_from_json,
    params_to_json,
    read_model_file,
    restore_validation_tables,
    validation_tables,
)
from .options import SolverOptions, SpatialOptions, dask_options, regularizer_pair, solver_options
from .predictive import PREDICTIVE_ATTRS, add_joint_offset, fit_predictive
from .regularizers import get_regularizer

__all__ = ["GLRM"]


class GLRM:
    """Generalized low rank model ``D ~ X^T Y`` fitted on the observed entries only.

    Parameters
    ----------
    rank : k, the number of components, or ``"auto"``: chosen among
        :data:`~lrm_cvx.validation.selection.AUTO_RANKS` by the rolling-origin validation of
        ``temporal="auto"`` (jointly with the temporal model; memoryless candidates only with
        ``temporal=None``), against rank :data:`~lrm_cvx.validation.selection.REFERENCE_RANK`:
        a higher rank gives the forecast more modes to carry, a lower one fewer to estimate
        from a few samples. ``rank_`` is the rank fitted, the table is ``selection_``.
    loss : ``"quadratic"`` (the paper), ``"huber"``, ``"absolute"``/``"l1"``, ``"quantile"``, or
        a :class:`~lrm_cvx.glrm.losses.Loss` instance (``Huber(delta=1.0)``, ``Quantile(0.9)``).
    reg : the regulariser of each column of ``X`` (times) and of ``Y`` (cells), or a pair
        ``(reg_x, reg_y)`` of one for each (``reg=(None, "ridge")``: ``Y`` only). A regulariser
        is ``None``, ``"ridge"``/``"l2"``, ``"l1"``, ``"nonneg"`` (weight 1), an instance
        (``Ridge(0.1)``, ``L1(0.1)``, ``NonNegative()``), or a callable ``fn(V)`` on a cvxpy
        Variable ``(k, n)`` returning a scalar expression (or ``(expression, constraints)``),
        summed over columns; callables are fitted by the cvxpy path.
    max_iter, tol : at most ``max_iter`` rounds (Y step then X step); stop when the relative
        decrease of the objective is below ``tol``.
    solver : ``"auto"`` (compiled fast path whenever the loss/regularisers allow), ``"fast"``
        (require it), or ``"cvxpy"`` (every block subproblem in cvxpy with Clarabel/SCS); or a
        :class:`~lrm_cvx.glrm.options.SolverOptions` naming one of them and the
        initialisation, ``init="svd"`` (SVD of the mean-filled matrix; randomized for large
        data, the default) or ``"random"``: ``solver=SolverOptions(init="random")``.
    random_state : seed / Generator for the initialisation.
    progress : show a tqdm progress bar.
    dask : for dask-backed data (docs/scaling.md): None (default) or a mapping of
        :func:`~.chunked.fit_chunked`'s options, keys among ``chunk_mb``, ``scratch_dir``,
        ``block_mb``, ``staging_options``, ``timings`` and ``keep_dask`` (True: keep ``Y_`` as
        a dask array of the persisted column chunks; default: a numpy array).
    offset, scale : fit a per-cell mean (``offset_``: jointly with the factors, the observed
        mean plus a correction with a prior worth one observation, glrm/offset.py; the observed
        mean alone with L1 / non-negative factors or ``solver="cvxpy"``) and/or divide by a
        per-cell std (``scale_``, the observed std, floored at ``predictive.SCALE_FLOOR`` times
        the median cell's) before the low-rank fit (``scale="residual"``: the residual's
        relative std, after it);
        prediction and planning undo them (docs/reconstruction.md).
    noise : ``"global"`` (the paper: one ``noise_std_``) or ``"per-cell"`` (``noise_var_``,
        per-cell training residual variance shrunk towards the global one; weights the fold-in
        and the planner's information; with ``spatial`` only its non-kriging fold-ins).
    spatial : None, a covariance model name (``"exponential"``, ``"matern32"``, ...) or
        ``"auto"`` (the family validated on the training residuals, ``kernel_selection_``,
        :mod:`~lrm_cvx.validation.kernel_selection`): fit a stationary covariance of the training
        residuals (``spatial_cov_``) for the trend + GP residual prediction. A
        :class:`~lrm_cvx.glrm.options.SpatialOptions` also fixes a family's anisotropy, its
        east-west over north-south range (grid cells; 1: isotropic, the default):
        ``spatial=SpatialOptions("exponential", anisotropy=2.0)``. ``spatial="auto"`` validates
        its own: the isotropic families against the same families at the
        directional-variogram estimate (:func:`~lrm_cvx.spatial.estimate_anisotropy`),
        docs/spatial.md.
    temporal : None (default: snapshots independent), ``"ar1"`` or ``"seasonal"``: after the
        fit, estimate linear-Gaussian dynamics of the latent columns of ``X_`` (``dynamics_``,
        :mod:`~lrm_cvx.glrm.dynamics`, docs/monitoring.md) for :meth:`monitor`. Needs a sorted,
        unique time coordinate and at least 3 snapshots (numpy input: one step per row).
        ``"auto"``: chosen by rolling-origin validation on the training snapshots, with a
        factor of the residual variances (``residual_inflation_``; :mod:`~lrm_cvx.glrm.
        selection`; the table is ``selection_``, saved with the model).
    calibration : None (default), ``"gaussian"`` / ``"conformal"`` or a dict of
        :func:`~lrm_cvx.validation.calibration.calibrate` keywords: after the fit, calibrate the
        variances on cross-validated fold-ins of the training snapshots (``calibration_``).

    Learned attributes: ``X_`` ``(component, time)``, ``Y_`` ``(component, cell)`` (DataArrays
    when fitted on xarray data, else ndarrays), ``region_``, ``objective_``, ``n_iter_``,
    ``converged_``, ``noise_std_``, ``unobserved_cells_``, ``rank_``, ``n_times_``, ``n_cells_``,
    ``n_observed_``, ``solver_``.

    ``noise_std_``: the RMS training residual, ``sqrt(SSE / (n_obs - p))`` with ``p = k (T +
    L_obs) - k^2`` the free parameters of a rank-k factorisation (else ``sqrt(SSE / n_obs)``).
    """

    def __init__(
        self,
        rank: int = 5,
        loss: Any = "quadratic",
        reg: Any = None,
        max_iter: int = 100,
        tol: float = 1e-4,
        solver: str | SolverOptions = "auto",
        random_state: Any = None,
        progress: bool = True,
        offset: bool = False,
        scale: bool = False,
        noise: str = "global",
        spatial: str | SpatialOptions | None = None,
        dask: Mapping[str, Any] | None = None,
        temporal: str | None = None,
        calibration: str | None = None,
    ) -> None:
        self.rank = rank
        self.loss = loss
        self.reg = reg
        self.max_iter = max_iter
        self.tol = tol
        self.solver = solver
        self.random_state = random_state
        self.progress = progress
        self.offset = offset
        self.scale = scale
        self.noise = noise
        self.spatial = spatial
        self.dask = dask
        self.temporal = temporal
        self.calibration = calibration

    # ------------------------------------------------------------------ sklearn protocol
    @classmethod
    def _param_names(cls) -> list[str]:
        sig = inspect.signature(cls.__init__)
        return [p for p in sig.parameters if p != "self"]

    @classmethod
    def recommended_params(cls) -> dict[str, Any]:
        """The constructor parameters the recommended setting sets (``RECOMMENDED``'s keys that
        are parameters of this class; docs/reconstruction.md)."""
        names = cls._param_names()
        return {k: v for k, v in RECOMMENDED.items() if k in names}

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor parameters, as stored."""
        return {p: getattr(self, p) for p in self._param_names()}

    def set_params(self, **params: Any) -> GLRM:
        """Set constructor parameters; returns ``self``."""
        names = self._param_names()
        for key, value in params.items():
            if key not in names:
                raise ModelError(f"unknown parameter {key!r}; valid: {names}")
            setattr(self, key, value)
        return self

    def __repr__(self) -> str:
        defaults = {
            p.name: p.default for p in inspect.signature(type(self).__init__).parameters.values()
        }
        parts = []
        for key, value in self.get_params().items():
            if key in defaults and _same(defaults[key], value):
                continue
            parts.append(f"{key}={value!r}")
        return f"GLRM({', '.join(parts)})"

    def _check_fitted(self) -> None:
        if not hasattr(self, "X_"):
            raise NotFittedError("this GLRM is not fitted yet: call fit(data) first")

    # ------------------------------------------------------------------ fit
    def fit(self, data: Any, mask: Any = None, region: Region | None = None) -> GLRM:
        """Fit ``X_`` and ``Y_`` to ``data``.

        ``data``: a ``(time, lat, lon)`` DataArray (NaN = missing; cells never observed are left
        out by ``Region.from_dataarray`` unless ``region`` is given), a ``(time, cell)``
        DataArray with ``region``, a ``(T, L)`` array with NaN, or a ``(T, L)`` array plus a
        boolean ``mask`` (True = observed; entries outside it are ignored). The fit reads the
        data zero-filled outside the mask: a C-contiguous float32/float64 array that already is
        is used without a copy, otherwise a zero-filled copy is made (the caller's array is
        never modified). Returns ``self``.
        """
        rank, rank_selection = self.rank, None
        _check_temporal(self.temporal, data)
        solver = solver_options(self.solver)
        dask, keep_dask = dask_options(self.dask)
        if isinstance(rank, str):  # "auto": validated before the fit (validation/selection.py)
            rank, rank_selection, region = self._choose_rank(data, mask, region)
        loss = get_loss(self.loss)
        reg_x, reg_y = (get_regularizer(r) for r in regularizer_pair(self.reg))
        rng = as_generator(self.random_state)
        if _is_dask(data) or _is_dask(mask):  # out of core, chunk by chunk on dask
            return self._fit_dask(data, mask, region, rank, loss, reg_x, reg_y, rng, solver,
                                  dask, keep_dask)
        D, M, region, times, owned = self._prepare(data, mask, region)
        offset = bool(self.offset) if isinstance(self.offset, (bool, np.bool_)) else False
        stats = check_data(D, M, rank, offset=offset,
                           times=None if times is None else times.values)
        keep = _keeps_stacked(self.temporal, D, region)  # for temporal="auto": no re-stacking
        pre = fit_predictive(self, D, M, region, stage="before",  # offset / scale (opt-in)
                             inplace=owned and not keep)
        stacked = None  # the snapshots as stacked, for temporal="auto" (no second stacking)
        if pre is not None:  # the init's mean fill needs the transformed data's sums
            if keep:
                stacked = D  # the fit reads the transformed copy: D stays as stacked
            D, owned = pre.pop("data"), True
            sc = getattr(self, "_pending_scale", None)
            colsum = (np.zeros_like(stats.colsum) if self.offset  # centred: sums are 0
                      else stats.colsum / sc)
            stats = DataStats(stats[0], stats[1], colsum)
        res = fit_glrm(
            D, M, rank, loss, reg_x, reg_y, max_iter=self.max_iter, tol=self.tol,
            init=solver.init, solver=solver.name, rng=rng, progress=bool(self.progress),
            stats=stats, overwrite_data=owned,  # our own copy: zero-filled in place
            offset=offset,
        )
        add_joint_offset(self, res.offset)  # the offset refined with the factors
        self._set_result(res, region, times, xarray=region is not None)
        fit_predictive(self, D, M, region, stage="after", pre=pre)  # noise / spatial (opt-in)
        self._fit_dynamics(M[-1], mask=M)
        del D, M
        self._validate_choices(data, stacked, rank_selection)
        _warn_if_static(self._Xv)
        return self

    def _fit_dask(self, data, mask, region, rank, loss, reg_x, reg_y, rng, solver, opts,
                  keep_dask) -> GLRM:
        from .chunked import STAGING_KEYS, fit_chunked
        from .fit import FitOptions
        from .predictive import check_options, data_scale, set_predictive, wants_residual_moments

        # the same options as in memory, computed chunk by chunk (every statistic is per cell)
        check_options(self, region is not None or getattr(data, "ndim", 0) == 3)
        extras: dict = {}
        opts = dict(opts)  # fit_chunked's keywords and the staging's
        staging = {**(opts.pop("staging_options", None) or {}),
                   **{key: opts.pop(key) for key in STAGING_KEYS if key in opts}}
        fit = FitOptions(max_iter=self.max_iter, tol=self.tol, init=solver.init,
                         solver=solver.name, rng=rng, progress=bool(self.progress),
                         offset=bool(self.offset))
        res, region, times, self._time_dim = fit_chunked(
            data, rank, loss, reg_x, reg_y, mask=mask, region=region,
            keep_dask=keep_dask, scale=data_scale(self),
            residual_moments=wants_residual_moments(self),
            residual_rows=20 if self.spatial is not None else None, extras=extras, fit=fit,
            staging_options=staging, **opts)
        self._set_result(res, region, times, xarray=region is not None)
        set_predictive(self, region, extras["offset"], extras["scale"], extras.get("moments"),
                       extras.get("sample"))
        self._fit_dynamics(extras["last_mask"], mask=extras.get("error_masks"))
        self._validate_choices(data)
        return self

    def _choose_rank(self, data: Any, mask: Any, region: Any) -> tuple[int, Any, Any]:
        """``rank="auto"``: ``(rank, selection, region)``, validated before the real fit
        (:func:`lrm_cvx.validation.choices.choose_rank`)."""
        return HOOKS.get("choose-rank")(self, data, mask, region, _is_dask(data))

    def _validate_choices(self, data: Any, stacked: np.ndarray | None = None,
                          selection: Any = None) -> None:
        """The choices validated on the training ``data``: ``temporal="auto"``'s
        ``dynamics_``, then ``calibration``'s ``calibration_``
        (:func:`lrm_cvx.validation.choices.validate_choices`)."""
        HOOKS.get("validate-choices")(self, data, stacked, selection)

    def _prepare(self, data, mask, region):
        """``(D, M, region, times, owned)`` from any supported input (no copy of clean arrays);
        ``owned`` is True when ``D`` is a copy the fit may overwrite."""
        times = None
        if isinstance(data, xr.DataArray):
            if mask is not None:
                raise DataError("mask is only accepted with a numpy array; a DataArray uses NaN")
            if data.ndim != 2 and data.ndim != 3:
                raise DataError(f"data must have dims (time, lat, lon), got {data.dims}")
            if data.ndim == 3:
                if region is None:
                    region = Region.from_dataarray(data)
                D = region.stack(data)
            else:
                if data.dims[-1] != "cell" or region is None:
                    raise DataError(
                        f"a 2-D DataArray must have dims (time, cell) and come with a region, "
                        f"got {data.dims}")
                D = region.stack(data)
            tdim = data.dims[0]
            times = data[tdim] if tdim in data.coords else xr.DataArray(
                np.arange(data.shape[0]), dims=(tdim,))
            times = times.rename("time") if tdim == "time" else times
            self._time_dim = tdim
            M = ~np.isnan(D)
            owned = data.ndim == 3 or not np.may_share_memory(D, data.values)  # 3-D: a gather
            return D, M, region, times, owned
        self._time_dim = "time"
        D = src = np.asarray(data)
        if D.ndim != 2:
            raise DataError(f"data must be a (T, L) array or a (time, lat, lon) DataArray, got "
                            f"shape {D.shape}")
        if not (np.issubdtype(D.dtype, np.floating) or np.issubdtype(D.dtype, np.integer)):
            raise DataError(f"data must be numeric, got dtype {D.dtype}")
        if D.dtype not in (np.float32, np.float64):
            D = D.astype(np.float64)
        D = np.ascontiguousarray(D)
        if mask is None:
            M = ~np.isnan(D)
        else:
            M = np.asarray(mask)
            if M.shape != D.shape:
                raise DataError(f"mask has shape {M.shape}, data has shape {D.shape}")
            if M.dtype != np.bool_:
                raise DataError(f"mask must be boolean (True = observed), got dtype {M.dtype}")
            M = np.ascontiguousarray(M)
        return D, M, None, None, not np.may_share_memory(D, src)

    def _set_result(self, res: FitResult, region, times, xarray: bool) -> None:
        k = res.X.shape[0]
        comp = np.arange(k)
        self.region_ = region
        self.n_times_, self.n_cells_ = res.X.shape[1], res.Y.shape[1]
        self.rank_ = int(k)
        self.n_features_in_ = self.n_cells_
        if xarray:
            tdim = getattr(self, "_time_dim", "time")
            tvals = times.values if times is not None else np.arange(self.n_times_)
            self.X_ = xr.DataArray(res.X, dims=("component", tdim),
                                   coords={"component": comp, tdim: tvals}, name="X")
            self.Y_ = xr.DataArray(res.Y, dims=("component", "cell"),
                                   coords={"component": comp, **region.cell_coords()}, name="Y")
        else:
            self.X_ = res.X
            self.Y_ = res.Y
        self.objective_ = np.asarray(res.objective, dtype=np.float64)
        self.n_iter_ = int(res.n_iter)
        self.converged_ = bool(res.converged)
        self.noise_std_ = float(res.noise_std)
        self.unobserved_cells_ = np.asarray(res.unobserved_cells, dtype=np.int64)
        self.n_observed_ = int(res.n_observed)
        self.solver_ = res.solver
        self.calibration_ = None  # a new fit invalidates a calibration (validation/calibration.py)
        self.selection_ = None  # temporal="auto"'s validation (validation/selection.py)
        self.dynamics_selection_ = None  # select_dynamics' table (validation/blending.py)

    # ------------------------------------------------------------------ accessors
    @property
    def X(self) -> np.ndarray:
        """The fitted ``X_`` as a ``(k, T)`` float64 numpy array (read-only property: the
        model's own array, not a copy; do not modify it). NotFittedError before ``fit``."""
        self._check_fitted()
        return np.asarray(getattr(self.X_, "values", self.X_), dtype=np.float64)

    @property
    def Y(self) -> np.ndarray:
        """The fitted ``Y_`` as a ``(k, L)`` float64 numpy array (read-only property, as
        :attr:`X`): what the planners and the fold-in take."""
        self._check_fitted()
        return np.asarray(getattr(self.Y_, "values", self.Y_), dtype=np.float64)

    @property
    def _Xv(self) -> np.ndarray:  # the old private name (tests use it)
        return self.X

    @property
    def _Yv(self) -> np.ndarray:
        return self.Y

    @property
    def Y_grid(self) -> xr.DataArray:
        """``Y_`` on the grid: ``(component, lat, lon)``, NaN off-region (needs a region)."""
        self._check_fitted()
        if self.region_ is None:
            raise ModelError("Y_grid needs a model fitted on a DataArray (with a region)")
        return self.region_.unstack(self.Y_, name="Y")

    def _to_data_units(self, Z: np.ndarray) -> np.ndarray:
        """``scale_ * Z + offset_`` in place (``Z (..., L)`` in fit units); a plain model's
        values are already in the data's units."""
        sc = getattr(self, "scale_", None)
        off = getattr(self, "offset_", None)
        if sc is not None:
            Z *= sc
        if off is not None:
            Z += off
        return Z

    def reconstruct(self) -> xr.DataArray | np.ndarray:
        """The fitted training snapshots in the data's units, ``scale_ * (X^T Y) + offset_``
        (just ``X^T Y`` for a plain model), float32: a ``(time, lat, lon)`` DataArray, or
        ``(T, L)`` for array input."""
        vals = self._to_data_units(self._Xv.T @ self._Yv).astype(np.float32)
        if self.region_ is None:
            return vals
        tdim = self.X_.dims[1]
        return self.region_.unstack(vals, dims=(tdim,), coords={tdim: self.X_[tdim].values},
                                    name="reconstruction")

    # ------------------------------------------------------------------ completion
    def _stack_snapshots(self, observations: Any) -> tuple[np.ndarray, bool, Any]:
        """``(values (n, L) with NaN, single, lead)``; ``lead`` = (dim name, coords) or None."""
        L = self.n_cells_
        region = self.region_
        if isinstance(observations, xr.DataArray):
            da = observations
            if da.dims and da.dims[-1] == "cell":
                vals = np.asarray(da.values, dtype=np.float64)
                if vals.shape[-1] != L:
                    raise DataError(f"observations have {vals.shape[-1]} cells, model has {L}")
            else:
                if region is None:
                    raise DataError("gridded observations need a model fitted with a region")
                vals = region.stack(da).astype(np.float64)
                if da.ndim < 2:
                    raise DataError(f"observations must have dims (lat, lon), got {da.dims}")
            if vals.ndim == 1:
                return vals[None], True, None
            if vals.ndim == 2:
                d0 = da.dims[0]
                return vals, False, (d0, da[d0].values if d0 in da.coords else None)
            raise DataError(f"observations have too many dims: {da.dims}")
        vals = np.asarray(observations, dtype=np.float64)
        if vals.ndim == 1 and vals.shape[0] == L:
            return vals[None], True, None
        if vals.ndim == 2 and vals.shape[1] == L:
            return vals, False, ("snapshot", None)
        raise DataError(
            "observations must be a DataArray (lat, lon)/(cell) (or with a leading dim), a "
            f"{{cell: value}} mapping, a (cells, values) tuple, or an array (L,)/(n, L) with "
            f"L={L}; got {type(observations).__name__}")

    def _observation_pairs(self, observations: Any) -> tuple[Any, np.ndarray] | None:
        """``(cells, values)`` of a ``{cell: value}`` mapping or a ``(cells, values)`` tuple
        (cells checked by the fold-in: integers only), else None (a map or a stack)."""
        if isinstance(observations, Mapping):
            cells = list(observations.keys())
            values = np.asarray(list(observations.values()), dtype=np.float64)
        elif isinstance(observations, tuple) and len(observations) == 2:
            cells, values = observations
            if np.ndim(cells) != 1 or np.ndim(values) != 1:
                raise DataError("a (cells, values) tuple needs two 1-D sequences, got shapes "
                                f"{np.shape(cells)} and {np.shape(values)}")
            values = np.asarray(values, dtype=np.float64)
        else:
            return None
        if len(cells) != values.size:
            raise DataError(f"{len(cells)} cells but {values.size} values")
        return cells, values

    def complete(self, observations: Any, ridge: float = 0.0, *, prior: str | None = None,
                 spatial: bool = False) -> xr.Dataset:
        """Region completion: predict the whole map from a partially observed snapshot.

        ``observations``: a DataArray ``(lat, lon)`` or ``(cell)`` with NaN, a ``{cell: value}``
        mapping, a ``(cells, values)`` tuple, or a stack of snapshots (a DataArray with a leading
        dim, or an ``(n, L)`` array with NaN). Solves ``x = (Y_S Y_S^T + ridge I)^-1 Y_S d_S``
        (the paper's pseudo-inverse when ``ridge = 0``) and returns a Dataset with
        ``prediction = Y^T x``, ``std`` (standard error of the predicted *mean*,
        ``sqrt(y_i^T Cov(x) y_i)`` with ``Cov(x) = noise_std_^2 (Y_S Y_S^T + ridge I)^-1``; it
        excludes the noise of a new observation, ``noise_std_``, stored as an attribute), ``x``
        and ``n_observations``, on the ``(lat, lon)`` grid when the model has a region, else on
        ``cell``.

        Options (docs/reconstruction.md): ``prior="empirical"`` is the Bayesian fold-in with
        the prior ``x ~ N(mean, cov)`` of the training columns of ``X``; ``spatial=True`` adds
        the kriged GP residual (needs ``spatial=`` at fit). A model fitted with ``offset``,
        ``scale`` or ``noise="per-cell"`` always uses them. Then ``std`` is the posterior std
        of the latent (noise-free) value. With ``prior="empirical"``, ``ridge > 0`` adds
        ``ridge / noise_std_^2 I`` to the prior precision.

        Cells of a mapping or tuple must be integer indices (``12.7`` is a DataError, never
        truncated); NaN values are dropped (not counted in ``n_observations``); a repeated cell
        is a repeated independent measurement; no observation at all gives the prior's map with
        a prior, or a ModelError without one. The algebra is
        :class:`~lrm_cvx.belief.posterior.LatentPosterior` (:meth:`latent_prior`).
        """
        self._check_fitted()
        ridge = check_positive(ridge, "ridge", error=ModelError)
        base = self.latent_prior(prior, ridge=ridge, spatial=spatial)
        pairs = self._observation_pairs(observations)
        if pairs is not None:  # one snapshot as (cells, values): NaN dropped, repeats allowed
            post = base.update(*pairs)
            pred, std = post.predict()
            x, n_obs, single, lead = post.mean, int(post.cells.size), True, None
        else:
            V, single, lead = self._stack_snapshots(observations)
            pred, std, x, n_obs = HOOKS.get("fold-in-snapshots")(base, V)
            if single:
                pred, std, x, n_obs = pred[0], std[0], x[0], int(n_obs[0])
        ds = self._completion_dataset(pred, std, x, n_obs, ridge, single, lead)
        if prior is not None or spatial or not self.is_plain_low_rank:
            ds.attrs.update(prior=str(prior), spatial=int(bool(spatial)),
                            std_kind="posterior std of the latent value")
            ds["std"].attrs["long_name"] = "posterior std of the latent value"
        return ds

    def latent_prior(self, prior: str | None = None, ridge: float = 0.0,
                     spatial: bool = False) -> Any:
        """The belief over a new snapshot's latent vector that :meth:`complete` folds in from
        (:class:`~lrm_cvx.belief.posterior.LatentPosterior`; ``prior``/``ridge``/``spatial`` as in
        :meth:`complete`). ``.update(cells, values)`` assimilates observations (data units),
        ``.predict()`` maps them, ``.information()`` is the planner's prior."""
        self._check_fitted()
        return HOOKS.get("model-prior")(self, prior, ridge=ridge, spatial=spatial)

    # ------------------------------------------------------------------ temporal dynamics
    def _foldin_covs(self, masks: Any) -> list[np.ndarray | None]:
        """``sigma^2 (Y_O W Y_O^T)^-1`` ``(k, k)`` per snapshot's training cells (rows of
        ``masks``), None where they do not determine ``x`` (:func:`.dynamics.foldin_covs`)."""
        nv = getattr(self, "noise_var_", None)
        w = 1.0 / (nv if nv is not None else max(self.noise_std_, 1e-300) ** 2)
        return foldin_covs(self._Yv, w, masks)

    def _fit_dynamics(self, last_mask: Any = None, mask: Any = None) -> None:
        """Set ``dynamics_`` from ``X_`` and its time coordinate (None when ``temporal`` is).

        ``mask`` ``(T, n)`` (the training cells of every snapshot; or any object giving the
        row of time ``t`` as ``mask[t]`` for the rows of :func:`~.dynamics.error_rows`, as the
        dask fit does): the average fold-in
        covariance of the columns (over at most 64 evenly spaced snapshots) corrects ``A`` and
        ``Q`` for the columns' estimation error (``error_cov`` of
        :func:`~lrm_cvx.glrm.dynamics.estimate_ar1`)."""
        self.dynamics_ = None
        if temporal_value(self.temporal) is None:
            return
        X = self._Xv
        times = (self.X_[self.X_.dims[1]] if isinstance(self.X_, xr.DataArray)
                 else np.arange(X.shape[1]))
        # the last snapshot's fold-in covariance from its training cells
        init_cov = None if last_mask is None else self._foldin_covs([last_mask])[0]
        error_cov = None
        if mask is not None:  # (T, n) array, or rows by time index (the dask fit's)
            covs = [c for c in self._foldin_covs(mask[t] for t in error_rows(X.shape[1]))
                    if c is not None]
            error_cov = np.mean(covs, axis=0) if covs else None
        kind = "ar1" if temporal_value(self.temporal) == "auto" else self.temporal
        self.dynamics_ = estimate_dynamics(kind, X, times, initial_cov=init_cov,
                                           error_cov=error_cov)

    def fit_dynamics(self, temporal: str = "ar1", **options: Any) -> GLRM:
        """Estimate ``dynamics_`` on an already fitted model (sets ``temporal``); ``options``
        go to :func:`~lrm_cvx.glrm.dynamics.estimate_ar1` (``shrinkage``). Returns ``self``."""
        self._check_fitted()
        if TEMPORAL.resolve(temporal) in (None, "none", "auto"):
            raise ModelError(f"temporal must be 'ar1' or 'seasonal', got {temporal!r}")
        self.temporal = temporal
        X = self._Xv
        times = (self.X_[self.X_.dims[1]] if isinstance(self.X_, xr.DataArray)
                 else np.arange(X.shape[1]))
        self.dynamics_ = estimate_dynamics(temporal, X, times, **options)
        return self

    def planner_kwargs(self, prior: str | None = "empirical", spatial: bool = False) -> dict:
        """Keyword arguments for :func:`~lrm_cvx.planning.plan_greedy` matching this model's
        fold-in: ``{"prior": belief}``, the :meth:`latent_prior` whose ``information()`` gives
        the prior precision, per-cell noise and per-cell scale (with ``spatial=True`` also
        ``prior_cov`` and ``spatial_cov`` for ``criterion="gp-variance"``)."""
        self._check_fitted()
        post = self.latent_prior(prior, spatial=spatial)
        if spatial and post.information()["prior_cov"] is None:
            raise ModelError("the gp-variance criterion needs prior='empirical' (a proper prior "
                             "covariance of the latent vector)")
        return {"prior": post}

    @property
    def is_plain_low_rank(self) -> bool:
        """True when the fitted model predicts with the paper's plain fold-in: no offset,
        scale or per-cell noise was fitted (so ``complete()`` is least squares on ``Y``)."""
        return (getattr(self, "offset_", None) is None
                and getattr(self, "scale_", None) is None
                and getattr(self, "noise_var_", None) is None)

    def _completion_dataset(self, pred, std, x, n_obs, ridge, single, lead) -> xr.Dataset:
        comp = np.arange(x.shape[-1])
        from .calibrated import residual_factor

        # the noise of a new snapshot's measurement (noise_std_ times its factors), fit units
        attrs = {"ridge": ridge, "noise_std": float(self.noise_std_
                                                    * np.sqrt(residual_factor(self))),
                 "std_kind": "standard error of the predicted mean (excludes noise_std)"}
        if single:
            lead_dims: tuple = ()
            lead_coords: dict = {}
            attrs["n_observations"] = n_obs
        else:
            name, coord = lead
            lead_dims = (name,)
            lead_coords = {name: coord} if coord is not None else {}
        if self.region_ is not None:
            pred_da = self.region_.unstack(pred, dims=lead_dims, coords=lead_coords,
                                        name="prediction")
            sda = self.region_.unstack(std, dims=lead_dims, coords=lead_coords, name="std")
        else:
            cc = {"cell": np.arange(self.n_cells_), **lead_coords}
            pred_da = xr.DataArray(pred, dims=lead_dims + ("cell",), coords=cc, name="prediction")
            sda = xr.DataArray(std, dims=lead_dims + ("cell",), coords=cc, name="std")
        xda = xr.DataArray(x, dims=lead_dims + ("component",),
                           coords={"component": comp, **lead_coords})
        data_vars = {"prediction": pred_da, "std": sda, "x": xda}
        if not single:
            data_vars["n_observations"] = xr.DataArray(np.asarray(n_obs), dims=lead_dims,
                                                       coords=lead_coords)
        ds = xr.Dataset(data_vars, attrs=attrs)
        ds["std"].attrs["long_name"] = "standard error of the predicted mean"
        return ds

    # ------------------------------------------------------------------ validation
    def _matrix(self, data: Any, mask: Any = None) -> tuple[np.ndarray, np.ndarray]:
        if isinstance(data, xr.DataArray):
            if mask is not None:
                raise DataError("mask is only accepted with a numpy array; a DataArray uses NaN")
            if self.region_ is None:
                raise DataError("a DataArray needs a model fitted with a region")
            D = np.asarray(self.region_.stack(data), dtype=np.float64)
            return D, ~np.isnan(D)
        try:
            D = np.ascontiguousarray(np.asarray(data, dtype=np.float64))
        except (TypeError, ValueError):
            raise DataError(f"data must be a numeric (T, L) array, got "
                            f"{type(data).__name__}") from None
        if mask is None:
            return D, ~np.isnan(D)
        M = np.asarray(mask)
        if M.dtype != np.bool_:
            raise DataError(f"mask must be boolean (True = observed), got dtype {M.dtype}")
        return D, np.ascontiguousarray(M)

    def score(self, data: Any, mask: Any = None) -> float:
        """Mean squared error, in the data's units squared, of the fitted values
        (:meth:`reconstruct`: ``scale_ * (X^T Y) + offset_``) against ``data`` on its observed
        entries.

        Entry-wise reconstruction error on the *training times* (``data`` has the training
        shape, e.g. the held-out part of :meth:`holdout`); not a fold-in of new snapshots.
        Observed entries must be finite (DataError otherwise).
        """
        self._check_fitted()
        D, M = self._matrix(data, mask)
        if D.shape != (self.n_times_, self.n_cells_):
            raise DataError(f"data has shape {D.shape}, the model was fitted on "
                            f"{(self.n_times_, self.n_cells_)}")
        if M.shape != D.shape:
            raise DataError(f"mask has shape {M.shape}, data has shape {D.shape}")
        n = int(np.count_nonzero(M))
        if n == 0:
            raise DataError("data has no observed entry to score")
        if not np.all(np.isfinite(D[M])):
            raise DataError("data has non-finite observed values (inf); use NaN for missing")
        X, Y = self._Xv, self._Yv
        if self.is_plain_low_rank:  # compiled residual pass, no (T, L) temporary
            pa, pb = K.pair_index(X.shape[0])
            nchunk = 8
            G = np.zeros((nchunk, D.shape[0], pa.size))
            h = np.zeros((nchunk, D.shape[0], X.shape[0]))
            f = np.zeros((nchunk, D.shape[0]))
            K.row_pass(D, M, X, Y, 0, 0.0, 0.0, pa, pb, nchunk, G, h, f)
            sse = float(f.sum())
        else:  # in data units, block of times by block of times
            sse = 0.0
            step = max(1, (1 << 22) // max(self.n_cells_, 1))
            for t0 in range(0, D.shape[0], step):
                m = M[t0:t0 + step]
                r = np.where(m, self._to_data_units(X[:, t0:t0 + step].T @ Y)
                             - np.where(m, D[t0:t0 + step], 0.0), 0.0)
                sse += float(np.einsum("ij,ij->", r, r))
        return sse / n

    @staticmethod
    def holdout(data: Any, fraction: float = 0.1, seed: Any = 0) -> tuple[Any, Any]:
        """Split the observed entries of ``data`` into ``(train, test)`` of the same type.

        A random ``fraction`` of the observed entries moves to ``test`` (NaN elsewhere), the rest
        stays in ``train``; every time keeps at least one training observation. ``fraction`` in
        (0, 1); infinite or non-numeric values raise DataError.
        """
        fraction = check_positive(fraction, "fraction", strict=True)
        if fraction >= 1:
            raise DataError(f"fraction must be in (0, 1), got {fraction}")
        rng = as_generator(seed)
        try:
            arr = data.values if isinstance(data, xr.DataArray) else np.asarray(data,
                                                                                 dtype=float)
        except (TypeError, ValueError):
            raise DataError(f"data must be a numeric array or DataArray, got "
                            f"{type(data).__name__}") from None
        if arr.ndim < 2 or not (np.issubdtype(arr.dtype, np.floating)
                                or np.issubdtype(arr.dtype, np.integer)):
            raise DataError(f"data must be a numeric (time, ...) array with at least 2 dims, "
                            f"got {arr.dtype} shape {arr.shape}")
        if not np.issubdtype(arr.dtype, np.floating):
            arr = arr.astype(np.float64)
        n_inf = int(np.count_nonzero(np.isinf(arr)))
        if n_inf:
            raise DataError(f"data has {n_inf} infinite values; use NaN for missing entries")
        obs = np.isfinite(arr)
        test = obs & (rng.random(arr.shape) < fraction)
        train_obs = obs & ~test
        lead = arr.shape[0]
        flat_train = train_obs.reshape(lead, -1)
        flat_test = test.reshape(lead, -1)
        empty = np.flatnonzero(~flat_train.any(axis=1) & flat_test.any(axis=1))
        if empty.size:
            first = flat_test[empty].argmax(axis=1)
            flat_test[empty, first] = False
            flat_train[empty, first] = True
        test = flat_test.reshape(arr.shape)
        train_obs = flat_train.reshape(arr.shape)
        train_v = np.where(train_obs, arr, np.nan).astype(arr.dtype, copy=False)
        test_v = np.where(test, arr, np.nan).astype(arr.dtype, copy=False)
        if isinstance(data, xr.DataArray):
            return data.copy(data=train_v), data.copy(data=test_v)
        return train_v, test_v

    def select_rank(self, data: Any, ranks: Any, fraction: float = 0.1,
                    seed: Any = 0) -> xr.Dataset:
        """Held-out error for each rank: fit a copy of this model on a training split of the
        observed entries (``fraction`` held out, ``seed``) and score it on the rest.

        Returns the table of every validated choice
        (:func:`~lrm_cvx.validation.search.selection_table`) over ``rank``: ``mse`` and
        ``rmse`` (held out, data units), ``ratio`` (to the first rank), the rank of the lowest
        error in ``attrs["choice"]`` (:func:`~lrm_cvx.validation.choices.select_rank`)."""
        return HOOKS.get("select-rank")(self, data, ranks, fraction, seed)

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | os.PathLike) -> None:
        """Write the fitted model to NetCDF (atomically)."""
        self._check_fitted()
        ds = self._to_dataset()
        with atomic_output(path) as tmp:
            ds.to_netcdf(tmp)

    def _to_dataset(self) -> xr.Dataset:
        X = self._Xv
        if _is_dask(self.Y_):  # a dask-backed Y_ is written chunk by chunk
            Y = self.Y_.data if isinstance(self.Y_, xr.DataArray) else self.Y_
        else:
            Y = self._Yv
        k = X.shape[0]
        if isinstance(self.X_, xr.DataArray):
            tdim = self.X_.dims[1]
            tvals = self.X_[tdim].values
        else:
            tdim, tvals = "time", np.arange(X.shape[1])
        ds = xr.Dataset(
            {
                "X": (("component", tdim), X),
                "Y": (("component", "cell"), Y),
                "objective": (("iteration",), self.objective_),
                "unobserved_cells": (("unobserved",), self.unobserved_cells_),
            },
            coords={"component": np.arange(k), tdim: tvals, "cell": np.arange(Y.shape[1])},
        )
        params, warn_custom = params_to_json(self.get_params())
        attrs = {
            "format": MODEL_FORMAT, "format_version": MODEL_FORMAT_VERSION,
            "params": params,
            "noise_std": self.noise_std_, "n_iter": self.n_iter_,
            "converged": int(self.converged_), "n_observed": self.n_observed_,
            "solver": self.solver_, "time_dim": str(tdim),
            "has_region": int(self.region_ is not None),
        }
        for name, arr in PREDICTIVE_ATTRS.arrays(self).items():
            ds[name] = (("cell",), arr)
        attrs.update(PREDICTIVE_ATTRS.attrs(self))
        if getattr(self, "dynamics_", None) is not None:
            dyn_vars, dyn_attrs = self.dynamics_.to_dataset_vars()
            for name, value in dyn_vars.items():
                ds[name] = value
            attrs.update(dyn_attrs)
        if getattr(self, "calibration_", None) is not None:
            attrs.update(self.calibration_.to_attrs())
        for table in validation_tables(self):  # temporal= / spatial="auto"'s choices
            ds = xr.merge([ds, table], combine_attrs="override")
            attrs.update(table.attrs)
        if warn_custom:
            attrs["note"] = ("custom callable regularisers cannot be saved; their repr is stored "
                             f"in params ({', '.join(warn_custom)})")
        if self.region_ is not None:
            reg_ds = self.region_.to_dataset()
            ds = xr.merge([ds, reg_ds])
            attrs["region_attrs"] = json.dumps(self.region_.attrs, default=str)
            attrs["region_name"] = "" if self.region_.name is None else str(self.region_.name)
        ds.attrs = attrs
        return ds

    @classmethod
    def load(cls, path: str | os.PathLike) -> GLRM:
        """Read a model written by :meth:`save` (the file is only read).

        DataError naming the file for a missing, unreadable, truncated or corrupt file, a
        NetCDF file that is not a GLRM model, a model file missing a variable or attribute
        (named), inconsistent factor shapes, or a file written by a newer lrm-cvx
        (``format_version`` above this version's).
        """
        ds, params = read_model_file(path)
        params = params_from_json(params)
        names = cls._param_names()
        model = cls(**{k: v for k, v in params.items() if k in names})
        tdim = ds.attrs.get("time_dim", "time")
        X = ds["X"].values
        Y = ds["Y"].values
        region = None
        if int(ds.attrs.get("has_region", 0)):
            name = ds.attrs.get("region_name") or None
            region = Region.from_dataset(ds, attrs=json.loads(ds.attrs.get("region_attrs", "{}")),
                                         name=name)
        res = FitResult(
            X=X, Y=Y, objective=list(ds["objective"].values), n_iter=int(ds.attrs["n_iter"]),
            converged=bool(int(ds.attrs["converged"])),
            unobserved_cells=ds["unobserved_cells"].values.astype(np.int64),
            n_observed=int(ds.attrs["n_observed"]), noise_std=float(ds.attrs["noise_std"]),
            solver=str(ds.attrs.get("solver", "fast")),
        )
        model._time_dim = tdim
        model._set_result(res, region, ds[tdim], xarray=region is not None)
        PREDICTIVE_ATTRS.restore(model, ds)
        model.dynamics_ = Dynamics.from_dataset(ds, time=ds[tdim].values[-1])
        from .calibrated import Calibration

        model.calibration_ = Calibration.from_attrs(ds.attrs)
        restore_validation_tables(model, ds)
        return model


def _is_dask(obj: Any) -> bool:
    if obj is None or isinstance(obj, np.ndarray):
        return False
    from .chunked import is_dask_backed

    return is_dask_backed(obj)


def _same(a: Any, b: Any) -> bool:
    try:
        return bool(a == b) and type(a) is type(b)
    except Exception:
        return a is b


def _keeps_stacked(temporal: Any, D: np.ndarray, region: Region | None) -> bool:
    """Whether the fit keeps its stacked training data beside the offset's transformed copy,
    for ``temporal="auto"``'s validation. Not for a region above
    ``refits.VALIDATION_MAX_CELLS``: its validation stacks its own window, and the fit
    transforms its gathered copy in place (one full-size copy less: 2.6 GB at paper scale)."""
    if temporal_value(temporal) != "auto" or D.ndim != 2 or region is None:
        return False
    return HOOKS.get("validation-window")(region) is None


def _check_temporal(temporal: Any, data: Any) -> None:
    """Refuse an unknown ``temporal`` or a DataArray without a time coordinate, before fitting."""
    if temporal_value(temporal) is None:
        return
    n_times = np.shape(data)[0] if np.ndim(data) >= 2 else 0
    if temporal_value(temporal) == "auto":
        HOOKS.get("check-auto-data")(data)
    if n_times < 3:
        raise ModelError(f"temporal={temporal!r} needs at least 3 snapshots to fit, got "
                         f"{n_times}")
    if isinstance(data, xr.DataArray):
        tdim = data.dims[0]
        if tdim not in data.coords:
            raise DataError(f"temporal={temporal!r} needs a time coordinate on the data's "
                            f"{tdim!r} dim, got none")
        from .dynamics import check_times

        check_times(data[tdim], f"data[{tdim!r}]")


def _warn_if_static(X: np.ndarray) -> None:
    """Warn when the fitted latent vectors ``X (k, T)`` do not vary over time (a constant
    field): every snapshot looks the same to the model, so there is nothing to plan for."""
    X = np.asarray(X, dtype=np.float64)
    if X.shape[1] < 2:
        return
    spread = float(np.ptp(X, axis=1).max())
    if spread <= 1e-9 * max(float(np.abs(X).max()), 1e-300):
        warnings.warn("the fitted latent vectors X_ do not vary over time (is the data constant "
                      "in time?): every snapshot looks the same to the model, a fold-in with "
                      "prior='empirical' returns the training mean, and planning has nothing "
                      "to learn", UserWarning, stacklevel=3)
