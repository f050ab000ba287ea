"""The Gaussian belief over one snapshot's latent vector.

Every fold-in of the project (``GLRM.complete``, the planner's prior terms, ``evaluate``'s
errors, the monitoring filter) is this module's algebra. The observation model of a fitted GLRM:

    value_j = offset_j + scale_j * (y_j^T x + r_j + e_j),    e_j ~ N(0, noise_var_j),

``r ~ GP(spatial_cov)`` an optional spatial residual (then the independent noise is the
covariance's nugget), ``offset``/``scale`` 0/1 when the model has none. The belief
``x ~ N(mean, cov)`` is kept in information form (``precision``, ``shift = precision @ mean``), so a
flat prior (the paper's least-squares fold-in, precision 0) is allowed and an update is a sum:

    precision' = precision + Y_S W Y_S^T,     shift' = shift + Y_S W z_S,

with ``z = (value - offset) / scale`` and ``W = diag(1 / noise_var_S)`` (``C^-1``, the GP residual's
covariance plus nugget, when spatial: generalised least squares). Costs: ``O(n k^2)`` per update
(``O(n^3)`` with the spatial residual: one Cholesky of the ``n x n`` observation covariance),
``O(L k^2)`` per predicted map.

Observations:

* cell indices must be integers (integral floats such as ``3.0`` are accepted; ``12.7`` is a
  :class:`~lrm_cvx.errors.DataError`, never truncated);
* NaN values are dropped and counted (``n_dropped``); infinite values are a DataError;
* no observations at all: the belief is returned unchanged;
* a repeated cell is a repeated independent measurement of the same value (each adds its
  information ``y y^T / noise_var``; sequential updates equal one batch update). With the spatial
  residual the repeats of one cell are averaged into one observation first (the residual ``r`` is
  shared; the nugget is not divided by the number of repeats, which is conservative).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse as sps

from .._validation import check_positive
from ..errors import DataError, ModelError
from .averaged import check_rows, row_kriging
from .observation import ObservationModel

__all__ = ["ObservationModel", "LatentPosterior", "PRIOR_KINDS", "check_cells", "empirical_moments",
           "average_repeats", "inverse_stack", "propagate_moments", "point_terms",
           "symmetric_part", "predict_many", "fold_in_maps", "pattern_groups"]

PRIOR_KINDS = ("empirical", "flat", "ridge", "custom")
_SINGULAR = 1e-12  # smallest eigenvalue / largest below this: the belief is improper


def check_cells(cells: Any, L: int, name: str = "cells") -> np.ndarray:
    """``cells`` as an int64 ``(n,)`` array of indices in ``[0, L)``.

    Integral floats (``3.0``) are accepted; non-integral ones (``12.7``), booleans, NaN and
    out-of-range indices raise DataError naming ``name``.
    """
    c = np.asarray(cells)
    if c.ndim == 0:
        c = c.reshape(1)
    if c.ndim != 1:
        raise DataError(f"{name} must be a 1-D sequence of cell indices, got shape {c.shape}")
    if c.size == 0:
        return np.zeros(0, dtype=np.int64)
    if c.dtype == np.bool_ or not (np.issubdtype(c.dtype, np.integer)
                                   or np.issubdtype(c.dtype, np.floating)):
        raise DataError(f"{name} must be integer cell indices, got dtype {c.dtype}")
    if np.issubdtype(c.dtype, np.floating):
        bad = ~np.isfinite(c) | (c != np.round(c))
        if bad.any():
            raise DataError(f"{name} must be integer cell indices, got {c[bad][0]!r} "
                            f"({int(bad.sum())} non-integer)")
    c = c.astype(np.int64)
    if c.min() < 0 or c.max() >= L:
        raise DataError(f"{name} must be indices in [0, {L}), got min {c.min()} max {c.max()}")
    return c


def symmetric_part(A: np.ndarray) -> np.ndarray:
    """The symmetric part of a matrix or of each matrix of a stack ``(..., k, k)``."""
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def inverse_stack(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric inverses of a precision/covariance matrix or of a stack of them ``(..., k,
    k)`` and whether each is (numerically) nonsingular ``(...)`` (where not, its entry is
    meaningless). One LAPACK eigendecomposition per matrix gives the condition check and the
    inverse; :class:`LatentPosterior` and the batched filter (``filter.batch_step``) share it."""
    ev, U = np.linalg.eigh(P)
    ok = ev[..., 0] > _SINGULAR * np.maximum(ev[..., -1], 1e-300)  # also False for NaN
    ev = np.where(ok[..., None], ev, 1.0)
    return symmetric_part((U / ev[..., None, :]) @ np.swapaxes(U, -1, -2)), ok


def _inverse(P: np.ndarray) -> np.ndarray | None:
    """Symmetric inverse of a precision/covariance matrix, None when (numerically) singular."""
    inv, ok = inverse_stack(P)
    return inv if ok else None


def propagate_moments(mean: np.ndarray, cov: np.ndarray, A: np.ndarray, Q: np.ndarray,
                      c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``A m + c`` and covariance ``sym(A S A^T + Q)`` after ``x' = A x + c + w``, ``w ~
    N(0, Q)``, of one belief (``(k,)``, ``(k, k)``) or of a stack (``(n, k)``, ``(n, k, k)``)."""
    m = (A @ mean[..., None])[..., 0] + c
    return m, symmetric_part(A @ cov @ np.swapaxes(A, -1, -2) + Q)


def point_terms(obs: ObservationModel, cells: np.ndarray, values: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, float, int]:
    """``(G, b, z^T W z, n)``: the information terms of a snapshot's point observations
    ``values`` (data units, finite) at ``cells`` (:meth:`ObservationModel.observation_terms`;
    with the spatial residual a cell's repeats are averaged first, and ``n`` counts distinct
    cells)."""
    z = obs.to_fit_units(cells, values)
    if obs.is_spatial:
        cells, z = _average_repeats(cells, z)
    G, b, zz = obs._terms(cells, z)
    return G, b, zz, cells.size


def empirical_moments(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(mean (k,), cov (k, k))`` of the training columns of ``X (k, T)`` (ddof 1, plus 1e-9 x
    its mean eigenvalue on the diagonal so it is invertible). When ``X`` does not vary over time
    (a constant field) the floor is 1e-21 x the mean's squared norm instead: the prior then pins
    every fold-in to the training mean, which is the right prediction, rather than failing."""
    X = np.asarray(X, dtype=np.float64)
    k, T = X.shape
    if T < 2:
        raise ModelError("prior='empirical' needs a model fitted on at least 2 times")
    S0 = np.atleast_2d(np.cov(X))
    mean = X.mean(axis=1)
    scale = np.trace(S0)
    if not scale > 1e-12 * float(mean @ mean):  # no spread over time
        scale = max(1e-12 * float(mean @ mean), scale)
    S0 = S0 + 1e-9 * max(scale, 1e-300) / k * np.eye(k)
    return mean, S0


# ============================================================================ the belief
@dataclass(frozen=True, eq=False)
class LatentPosterior:
    """Gaussian belief ``x ~ N(mean, cov)`` over one snapshot's latent vector (immutable).

    Kept in information form: ``precision (k, k)`` and ``shift = precision @ mean (k,)``; a flat
    (improper) belief has ``precision`` 0 and ``mean``/``cov`` raise ModelError until enough
    observations make it proper (``is_proper``). ``cells``/``values`` are the observations of
    this snapshot assimilated so far (data units, NaN dropped; ``n_dropped`` counts the NaN), and
    ``base_precision``/``base_shift`` the belief before them (the spatial GLS is re-solved from
    it over all of the snapshot's cells). Build with :meth:`prior` or :meth:`from_moments`.
    """

    obs_model: ObservationModel
    precision: np.ndarray
    shift: np.ndarray
    base_precision: np.ndarray
    base_shift: np.ndarray
    cells: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    n_dropped: int = 0
    day_q: float = 0.0  # innovation statistic of this snapshot's observations (adaptive scale)
    day_n: float = 0.0  # its degrees of freedom
    scale_q: float = 0.0  # evidence about the scale carried from earlier snapshots (discounted)
    scale_n: float = 0.0
    rows: Any = None  # averaged observations of this snapshot (CSR (m, L), data-unit weights)
    row_values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    row_noise: np.ndarray = field(default_factory=lambda: np.zeros(0))  # fit units, per row

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_moments(cls, obs_model: ObservationModel, mean: Any = None, cov: Any = None, *,
                     precision: Any = None) -> LatentPosterior:
        """A belief from ``mean (k,)`` and ``cov (k, k)`` (or ``precision``; neither: flat)."""
        k = obs_model.k
        m = np.zeros(k) if mean is None else np.asarray(mean, dtype=np.float64)
        if m.shape != (k,) or not np.all(np.isfinite(m)):
            raise ModelError(f"mean must be a finite ({k},) array, got shape {m.shape}")
        if cov is not None and precision is not None:
            raise ModelError("give cov or precision, not both")
        if cov is not None:
            S = np.asarray(cov, dtype=np.float64)
            if S.shape != (k, k) or not np.all(np.isfinite(S)):
                raise ModelError(f"cov must be a finite ({k}, {k}) matrix, got shape {S.shape}")
            P = _inverse(symmetric_part(S))
            if P is None:
                raise ModelError("cov must be symmetric positive definite")
        elif precision is not None:
            P = np.asarray(precision, dtype=np.float64)
            if P.shape != (k, k) or not np.all(np.isfinite(P)):
                raise ModelError(f"precision must be a finite ({k}, {k}) matrix")
            P = symmetric_part(P)
            if np.linalg.eigvalsh(P)[0] < -1e-10 * max(np.abs(P).max(), 1e-300):
                raise ModelError("precision must be positive semi-definite")
        else:
            P = np.zeros((k, k))
        h = P @ m
        post = cls(obs_model, P, h, P, h)
        if cov is not None:  # keep the given covariance exactly (no round trip)
            post.__dict__["cov"] = symmetric_part(np.asarray(cov, dtype=np.float64))
            post.__dict__["mean"] = m.copy()
        return post

    @classmethod
    def prior(cls, model_or_obs: Any, kind: str = "empirical", ridge: float = 0.0,
              mean: Any = None, cov: Any = None, *, spatial: bool | None = None
              ) -> LatentPosterior:
        """The belief before any observation of a snapshot.

        ``model_or_obs``: a fitted GLRM (its :meth:`ObservationModel.from_model` with
        ``spatial``) or an :class:`ObservationModel`. ``kind``:

        * ``"empirical"``: ``N(mean(X_), cov(X_))`` over the model's training times (needs a model);
        * ``"flat"``: no prior, the paper's least-squares fold-in; with ``ridge > 0`` it is the
          ridge prior below (the paper's ridge);
        * ``"ridge"``: ``N(0, ref_var / ridge I)``, i.e. ``(Y_S Y_S^T + ridge I)^-1`` for the
          plain model (``ridge = 0``: flat);
        * ``"custom"``: ``N(mean, cov)`` as given.
        """
        if isinstance(model_or_obs, ObservationModel):
            obs, model = model_or_obs, None
        else:
            obs, model = ObservationModel.from_model(model_or_obs, spatial=spatial), model_or_obs
        if kind not in PRIOR_KINDS:
            raise ModelError(f"prior kind must be one of {PRIOR_KINDS}, got {kind!r}")
        ridge = check_positive(ridge, "ridge", error=ModelError)
        if kind != "custom" and (mean is not None or cov is not None):
            raise ModelError(f"mean/cov are for kind='custom', not {kind!r}")
        if kind == "custom":
            if cov is None:
                raise ModelError("kind='custom' needs cov (a (k, k) covariance)")
            return cls.from_moments(obs, mean, cov)
        if kind == "empirical":
            if model is None:
                raise ModelError("kind='empirical' needs the fitted model (its X_), not an "
                                 "ObservationModel")
            m0, S0 = empirical_moments(model.X)
            return cls.from_moments(obs, m0, S0)
        if ridge > 0:
            return cls.from_moments(obs, None, precision=(ridge / obs.ref_var) * np.eye(obs.k))
        return cls.from_moments(obs)

    # ------------------------------------------------------------------ moments
    @property
    def k(self) -> int:
        return self.obs_model.k

    @cached_property
    def _cov_or_none(self) -> np.ndarray | None:
        return _inverse(self.precision)

    @property
    def is_proper(self) -> bool:
        """True when the precision is nonsingular (mean and covariance are defined)."""
        return "cov" in self.__dict__ or self._cov_or_none is not None

    @property
    def is_flat(self) -> bool:
        """True when the precision is exactly zero (no prior, no observation)."""
        return not np.any(self.precision)

    def _need_proper(self) -> None:
        if not self.is_proper:
            k, n = self.k, self.cells.size
            raise ModelError(
                f"the fold-in is singular: {n} observation(s) do not determine the rank-{k} "
                f"latent vector (the paper's fold-in needs at least {k} cells with independent "
                "factors); observe more cells, pass ridge > 0 or use prior='empirical'")

    @cached_property
    def cov(self) -> np.ndarray:
        """Posterior covariance ``(k, k)`` (fit units); ModelError when improper."""
        self._need_proper()
        return self._cov_or_none

    @cached_property
    def mean(self) -> np.ndarray:
        """Posterior mean ``(k,)``; ModelError when improper."""
        return self.cov @ self.shift

    # ------------------------------------------------------------------ the fold-in
    def update(self, cells: Any, values: Any) -> LatentPosterior:
        """Assimilate ``values`` (data units) at ``cells`` of this snapshot; a new belief.

        NaN values are dropped (counted in ``n_dropped``); no observation returns ``self``.
        Integer cells only (DataError otherwise); a repeated cell is a repeated independent
        measurement (averaged first with the spatial residual, see the module docstring).
        """
        obs = self.obs_model
        cells = check_cells(cells, obs.n_cells)
        v = np.asarray(values, dtype=np.float64)
        if v.ndim == 0 and cells.size == 1:
            v = v.reshape(1)
        if v.shape != cells.shape:
            raise DataError(f"values has shape {v.shape}, cells has shape {cells.shape}")
        if np.isinf(v).any():
            raise DataError("values must be finite (NaN marks a missing value)")
        keep = ~np.isnan(v)
        dropped = int(v.size - keep.sum())
        cells, v = cells[keep], v[keep]
        if cells.size == 0:
            return self._only_dropped(dropped)
        all_cells = np.concatenate([self.cells, cells])
        all_values = np.concatenate([self.values, v])
        adaptive = obs.adaptive_dof is not None
        has_rows = self.rows is not None and self.rows.shape[0] > 0
        if obs.is_spatial and has_rows:  # the GLS over today's cells and averaged rows
            G, b, zz = obs.row_terms(*self._fit_rows_all(all_cells, all_values))
            P, h = self.base_precision + G, self.base_shift + b
            n_all = np.unique(all_cells).size + self.rows.shape[0]
        elif obs.is_spatial:  # correlated residuals: re-solve the GLS over all of today's cells
            G, b, zz, n_all = point_terms(obs, all_cells, all_values)
            P, h = self.base_precision + G, self.base_shift + b
        else:
            G, b = obs.observation_terms(cells, obs.to_fit_units(cells, v))
            P, h = self.precision + G, self.shift + b
            if adaptive:  # the innovation is over all of today's cells, from the day's prior
                G, b, zz = obs._terms(all_cells, obs.to_fit_units(all_cells, all_values))
                if has_rows:
                    G2, b2, zz2 = obs.row_terms(*self._fit_rows_only())
                    G, b, zz = G + G2, b + b2, zz + zz2
            n_all = all_cells.size + (self.rows.shape[0] if has_rows else 0)
        dq, dn = self._day_evidence(G, b, zz, n_all) if adaptive else (0.0, 0.0)
        return LatentPosterior(obs, symmetric_part(P), h, self.base_precision, self.base_shift,
                               all_cells, all_values, self.n_dropped + dropped, dq, dn,
                               self.scale_q, self.scale_n, self.rows, self.row_values,
                               self.row_noise)

    def _day_evidence(self, G: np.ndarray, b: np.ndarray, zz: float, n_all: int
                      ) -> tuple[float, float]:
        """``(day_q, day_n)``: the innovation statistic of the day's observations against the
        belief before them (the adaptive scale's evidence; ``(0, 0)`` when it has none)."""
        q, n_eff = _innovation(self.base_precision, self.base_shift, G, b, zz, n_all)
        return (q, float(n_eff)) if n_eff > 0 and np.isfinite(q) else (0.0, 0.0)

    def _only_dropped(self, dropped: int) -> LatentPosterior:
        """This belief, bit for bit, with ``dropped`` more NaN values counted."""
        if dropped == 0:
            return self
        same = replace(self, n_dropped=self.n_dropped + dropped)
        same.__dict__.update({k: self.__dict__[k] for k in ("cov", "mean") if k in self.__dict__})
        return same

    def _fit_rows_only(self, rows: Any = None, values: Any = None, noise: Any = None
                       ) -> tuple[sps.csr_matrix, np.ndarray, np.ndarray]:
        """The averaged rows (default the belief's) in fit units ``(B, z, noise)``."""
        B, z, _ = self.obs_model.fit_rows(self.rows if rows is None else rows,
                                          self.row_values if values is None else values)
        return B, z, self.row_noise if noise is None else noise

    def _fit_rows_all(self, cells: np.ndarray, values: np.ndarray, rows: Any = None,
                      row_values: Any = None, noise: Any = None
                      ) -> tuple[sps.csr_matrix, np.ndarray, np.ndarray]:
        """Every observation of the snapshot in fit units ``(B, z, noise)``: the point cells
        (repeats averaged) as one-hot rows, then the averaged rows (default the belief's)."""
        obs = self.obs_model
        uc, zc = _average_repeats(cells, obs.to_fit_units(cells, values))
        one = sps.csr_matrix((np.ones(uc.size), (np.arange(uc.size), uc)),
                             shape=(uc.size, obs.n_cells))
        rows = self.rows if rows is None else rows
        if rows is None or rows.shape[0] == 0:
            return one, zc, obs.noise_at(uc)
        B, z, nz = self._fit_rows_only(rows, row_values, noise)
        return sps.vstack([one, B]).tocsr(), np.r_[zc, z], np.r_[obs.noise_at(uc), nz]

    def update_rows(self, rows: Any, values: Any, errors: str = "independent"
                    ) -> LatentPosterior:
        """Assimilate averaged observations, a new belief: ``values[i]`` (data units) is the
        weighted average ``rows[i] @ d`` of the snapshot (``rows``: ``(m, L)`` weights, sparse
        or dense, e.g. a sensor's, :mod:`lrm_cvx.planning.sensors`). Each is one observation of
        the row ``Y B_i`` (``B = rows diag(scale)``) with noise variance ``sum_j B_ij^2
        noise_var_j`` (``errors="independent"``) or ``(sum_j |B_ij| sigma_j)^2`` (``"shared"``:
        equal cell errors within an observation); observations are independent. With the
        spatial residual: the GLS over all of the snapshot's observations, covariance
        ``B K B^T + diag(noise)`` (noise from the nugget). NaN values are dropped
        (``n_dropped``). A one-hot row is a point observation (:meth:`update`)."""
        obs = self.obs_model
        A, v = check_rows(rows, obs.n_cells, values)
        keep = ~np.isnan(v)
        dropped = int(v.size - keep.sum())
        A, v = A[np.flatnonzero(keep)], v[keep]
        if A.shape[0] == 0:
            return self._only_dropped(dropped)
        B, z, noise = obs.fit_rows(A, v, errors)
        had = self.rows is not None and self.rows.shape[0] > 0
        all_rows = sps.vstack([self.rows, A]).tocsr() if had else A
        all_rv = np.concatenate([self.row_values, v]) if had else v
        all_noise = np.concatenate([self.row_noise, noise]) if had else noise
        adaptive = obs.adaptive_dof is not None
        if obs.is_spatial:
            G, b, zz = obs.row_terms(*self._fit_rows_all(self.cells, self.values, all_rows,
                                                         all_rv, all_noise))
            P, h = self.base_precision + G, self.base_shift + b
        else:
            G, b, zz = obs.row_terms(B, z, noise)
            P, h = self.precision + G, self.shift + b
            if adaptive:
                G, b, zz = obs.row_terms(*self._fit_rows_only(all_rows, all_rv, all_noise))
                if self.cells.size:
                    G2, b2, zz2 = obs._terms(self.cells,
                                             obs.to_fit_units(self.cells, self.values))
                    G, b, zz = G + G2, b + b2, zz + zz2
        n_all = (np.unique(self.cells).size if obs.is_spatial else self.cells.size) \
            + all_rows.shape[0]
        dq, dn = self._day_evidence(G, b, zz, n_all) if adaptive else (0.0, 0.0)
        return LatentPosterior(obs, symmetric_part(P), h, self.base_precision, self.base_shift,
                               self.cells, self.values, self.n_dropped + dropped, dq, dn,
                               self.scale_q, self.scale_n, all_rows, all_rv, all_noise)

    @property
    def variance_scale(self) -> float:
        """The multiplier of every output variance. Fixed calibration: the model's
        ``obs_model.variance_scale`` ``s0``. Adaptive (``obs_model.adaptive_dof = nu``): the
        conjugate estimate ``(nu s0 + q_carried + q_day) / (nu + n_carried + n_day)``, with
        ``q_day`` the innovation statistic of this snapshot's observations (``n_day`` dof) and
        ``q_carried`` / ``n_carried`` the earlier snapshots' evidence, discounted by
        ``scale_discount`` per step (:meth:`propagate`)."""
        obs = self.obs_model
        if obs.adaptive_dof is None:
            return obs.variance_scale
        nu = float(obs.adaptive_dof)
        return float((nu * obs.variance_scale + self.scale_q + self.day_q)
                     / (nu + self.scale_n + self.day_n))

    def carried_evidence(self, steps: int = 1) -> tuple[float, float]:
        """``(q, n)`` of the scale evidence passed on to a snapshot ``steps`` later."""
        d = float(self.obs_model.scale_discount) ** max(int(steps), 1)
        return d * (self.scale_q + self.day_q), d * (self.scale_n + self.day_n)

    def innovation(self, cells: Any, values: Any) -> tuple[float, int]:
        """``(q, n_eff)``: the squared Mahalanobis norm of the innovations of ``values`` at
        ``cells`` (data units, NaN dropped) under this belief as the prior, ``q = e^T S_e^-1 e``
        with ``e = z - Y_S^T m`` and ``S_e = Y_S^T cov Y_S + R`` (``R`` the noise, or the spatial
        covariance), unscaled (``variance_scale`` 1), and its degrees of freedom ``n_eff`` (the
        number of values, minus the latent directions the belief leaves flat). For data from
        the model ``q ~ s chi2(n_eff)`` with ``s`` the true variance scale."""
        obs = self.obs_model
        cells = check_cells(cells, obs.n_cells)
        v = np.asarray(values, dtype=np.float64).reshape(cells.shape)
        keep = ~np.isnan(v)
        cells, v = cells[keep], v[keep]
        z = obs.to_fit_units(cells, v)
        if obs.is_spatial:
            cells, z = _average_repeats(cells, z)
        G, b, zz = obs._terms(cells, z)
        return _innovation(self.precision, self.shift, G, b, zz, cells.size)

    def batch_means(self, cells: Any, values: Any) -> tuple[np.ndarray, np.ndarray]:
        """Posterior means of ``m`` independent updates that share ``cells``: ``values (m, n)``
        (data units, NaN where a snapshot lacks a cell). Returns ``means (m, k)`` (NaN rows where
        the belief stays improper) and ``proper (m,)``. Equal to ``[self.update(cells,
        v).mean for v in values]``, vectorised (``O(m n k^2)``, no Python loop); without the
        spatial residual only (the evaluation's exact error path)."""
        obs = self.obs_model
        if obs.is_spatial:
            raise ModelError("batch_means is for the observation model without the spatial "
                             "residual (use update(...).predict() for kriging)")
        cells = check_cells(cells, obs.n_cells)
        V = np.asarray(values, dtype=np.float64)
        if V.ndim != 2 or V.shape[1] != cells.size:
            raise DataError(f"values must have shape (m, {cells.size}), got {V.shape}")
        if np.isinf(V).any():
            raise DataError("values must be finite (NaN marks a missing value)")
        ok = ~np.isnan(V)
        w = ok / obs.noise_at(cells)
        wz = w * np.where(ok, obs.to_fit_units(cells, np.where(ok, V, 0.0)), 0.0)
        Ys = obs.Y[:, cells]
        P = self.precision + np.einsum("tn,kn,jn->tkj", w, Ys, Ys, optimize=True)
        h = self.shift + wz @ Ys.T
        ev, U = np.linalg.eigh(0.5 * (P + P.transpose(0, 2, 1)))
        proper = ev[:, 0] > _SINGULAR * np.maximum(ev[:, -1], 1e-300)
        ev = np.where(proper[:, None], ev, 1.0)
        means = np.einsum("tkj,tj->tk", U, np.einsum("tkj,tk->tj", U, h) / ev)
        means[~proper] = np.nan
        return means, proper

    @property
    def n_samples(self) -> int:
        """The samples of this snapshot the belief holds: its distinct cells plus its averaged
        rows (what a calibration's design size counts)."""
        rows = 0 if self.rows is None else int(self.rows.shape[0])
        return int(np.unique(self.cells).size) + rows

    # ------------------------------------------------------------------ prediction
    def _spatial(self, spatial: bool | None) -> bool:
        if spatial is None:
            return self.obs_model.is_spatial
        if spatial and not self.obs_model.is_spatial:
            raise ModelError("spatial=True needs an observation model with a spatial residual "
                             "(a model fitted with spatial='exponential' or another covariance)")
        return bool(spatial)

    def _latent_var(self, spatial: bool, cells: Any = None) -> tuple[np.ndarray, np.ndarray]:
        """``(mean, var)`` of the noise-free value at ``cells`` (default all), fit units."""
        obs = self.obs_model
        Y = obs.Y if cells is None else obs.Y[:, cells]
        m, S = self.mean, self.cov
        mu = Y.T @ m
        if not spatial:
            return mu, np.maximum(np.einsum("ai,ai->i", Y, S @ Y), 0.0)
        from .. import spatial as sp

        cov = obs.spatial_cov
        region = obs.region
        if self.rows is not None and self.rows.shape[0] > 0:
            B, z, noise = self._fit_rows_all(self.cells, self.values)
            return row_kriging(obs.Y, B, z, noise, self.mean, self.cov, cov, region, cells)
        uc, zc = _average_repeats(self.cells, obs.to_fit_units(self.cells, self.values))
        Ys = obs.Y[:, uc]
        res = zc - Ys.T @ m
        if (cells is None and cov.metric == "grid" and cov.nugget > 0 and cov.sill > 0
                and float(uc.size) * obs.n_cells > sp.FFT_KRIGE_MIN_WORK):
            # the whole map: FFT convolutions instead of an (L, n) covariance block
            r_mu, var, _ = sp.krige_grid_fft(cov, region, uc, res, Ys=Ys, Yall=obs.Y, cov_x=S)
            return mu + r_mu, np.maximum(var, 0.0)
        tg = np.arange(obs.n_cells) if cells is None else np.asarray(cells)
        meth = "direct" if uc.size <= sp.MAX_DIRECT else "neighbors"
        r_mu, var = sp.krige_core(
            cov, cov.points(region, uc), res[:, None],
            cov.points(region, tg), method=meth, neighbors=32, cutoff=1e-6,
            want_var=True, Ys=Ys, Yt=lambda sel: obs.Y[:, tg[sel]], cov_x=S)
        return mu + r_mu[0], np.maximum(var, 0.0)

    def predict(self, spatial: bool | None = None, cells: Any = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """``(mean, std)`` of the noise-free value at every cell (or at ``cells``), in data units.

        ``std`` is the posterior std of the latent value (it excludes the noise of a new
        measurement: :meth:`predictive_std`). ``spatial`` (None: the observation model's
        setting) adds the kriged residual and its variance (universal kriging with a Bayesian
        trend prior; the GP conditional of ``Y^T x + r``).
        """
        sp_ = self._spatial(spatial)
        if cells is not None:
            cells = check_cells(cells, self.obs_model.n_cells)
        mu, var = self._latent_var(sp_, cells)
        return self.obs_model.to_data_units(mu, np.sqrt(self.variance_scale * var),
                                            slice(None) if cells is None else cells)

    def predictive_std(self, spatial: bool | None = None, cells: Any = None) -> np.ndarray:
        """Std of a new measurement at every cell (or ``cells``), data units: the latent
        variance plus the noise (``noise_var``; the nugget with the spatial residual)."""
        return self.predict_all(spatial, cells)[2]

    def predict_all(self, spatial: bool | None = None, cells: Any = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(mean, std, predictive_std)``: :meth:`predict` and :meth:`predictive_std` from one
        evaluation of the latent variance (one kriging pass instead of two; the maps of
        ``MonitorState.forecast``/``predict``)."""
        obs = self.obs_model
        sp_ = self._spatial(spatial)
        if cells is not None:
            cells = check_cells(cells, obs.n_cells)
        idx = slice(None) if cells is None else cells
        mu, var = self._latent_var(sp_, cells)
        mean, std = obs.to_data_units(mu, np.sqrt(self.variance_scale * var), idx)
        return mean, std, _predictive_std(obs, var, sp_, idx, self.variance_scale)

    def interval_multipliers(self, levels: Any = (0.68, 0.95)) -> np.ndarray:
        """Half-widths of the central ``levels`` intervals in units of :meth:`predictive_std`:
        the conformal thresholds of the model's calibration (``calibrate(...,
        method="conformal")``; interpolated at this belief's :attr:`n_samples` where it has
        per-size thresholds), else the normal quantiles. A level
        outside (0, 1) is a ModelError naming it."""
        from ..glrm.calibrated import check_level, gaussian_multiplier

        cal = self.obs_model.calibration
        lv = [check_level(v, "level") for v in np.atleast_1d(levels)]
        if cal is not None and getattr(cal, "is_conformal", False):
            return np.array([cal.multiplier(v, self.n_samples) for v in lv])
        return np.asarray(gaussian_multiplier(lv), dtype=np.float64)

    def interval(self, level: float = 0.95, spatial: bool | None = None, cells: Any = None,
                 multiplier: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(lower, upper)``: the central ``level`` predictive interval of a new measurement at
        every cell (or ``cells``), data units: ``mean +- m * predictive_std`` with ``m`` from
        :meth:`interval_multipliers` (or the given ``multiplier``, e.g. an online
        :class:`~lrm_cvx.glrm.calibrated.AdaptiveConformal`'s)."""
        m = float(self.interval_multipliers(level)[0]) if multiplier is None else float(multiplier)
        mean, _, pstd = self.predict_all(spatial, cells)
        half = m * pstd if np.isfinite(m) else np.full_like(pstd, np.inf)
        return mean - half, mean + half

    def interval_coverage(self, values: Any, cells: Any = None,
                          levels: Any = (0.68, 0.95)) -> np.ndarray:
        """Fraction of ``values`` (data units at ``cells``, default every cell; NaN left out)
        inside this belief's :meth:`interval` per level, ``(len(levels),)``."""
        from ..glrm.calibrated import interval_coverage

        mean, _, pstd = self.predict_all(None, cells)
        return interval_coverage(values, mean, pstd, tuple(np.atleast_1d(levels)),
                                 multipliers=self.interval_multipliers(levels))

    # ------------------------------------------------------------------ planner and filter
    def information(self) -> dict[str, Any]:
        """The planner's prior terms (keyword arguments of
        :func:`~lrm_cvx.planning.plan_greedy`): ``prior_precision`` (None when flat),
        ``noise_var`` (fit units; the spatial covariance's total variance when spatial),
        ``target_weights`` (``scale^2``: variances in data units, or None), and with the
        spatial residual ``prior_cov`` (the latent covariance; None when improper) and
        ``spatial_cov``. With the spatial residual and cells already assimilated, the residual's
        conditioning on them is not carried (only the latent covariance is)."""
        obs = self.obs_model
        out: dict[str, Any] = {
            "prior_precision": None if self.is_flat else self.precision.copy(),
            "noise_var": obs.spatial_cov.total_variance if obs.is_spatial else obs.noise_var,
            "target_weights": None if obs.scale is None else obs.scale ** 2,
        }
        if obs.is_spatial:
            out["prior_cov"] = self.cov.copy() if self.is_proper else None
            out["spatial_cov"] = obs.spatial_cov
        return out

    def propagate(self, A: Any, Q: Any, c: Any = None, steps: int = 1) -> LatentPosterior:
        """The belief about the next snapshot under ``x' = A x + c + w``, ``w ~ N(0, Q)``:
        mean ``A m + c``, covariance ``A S A^T + Q``. Clears the cells (a new snapshot).
        ``A = 0`` is allowed from any belief (then it is ``N(c, Q)`` exactly). The adaptive
        scale's evidence is carried over ``steps`` steps (:meth:`carried_evidence`)."""
        k = self.k
        A = np.asarray(A, dtype=np.float64)
        Q = np.asarray(Q, dtype=np.float64)
        if A.shape != (k, k) or not np.all(np.isfinite(A)):
            raise ModelError(f"A must be a finite ({k}, {k}) matrix, got shape {A.shape}")
        if Q.shape != (k, k) or not np.all(np.isfinite(Q)):
            raise ModelError(f"Q must be a finite ({k}, {k}) matrix, got shape {Q.shape}")
        c = np.zeros(k) if c is None else np.asarray(c, dtype=np.float64)
        if c.shape != (k,) or not np.all(np.isfinite(c)):
            raise ModelError(f"c must be a finite ({k},) vector, got shape {c.shape}")
        if not np.any(A):
            out = LatentPosterior.from_moments(self.obs_model, c, Q)
        else:
            out = LatentPosterior.from_moments(self.obs_model,
                                               *propagate_moments(self.mean, self.cov, A, Q, c))
        if self.obs_model.adaptive_dof is not None:
            q, n = self.carried_evidence(steps)
            carried = replace(out, scale_q=q, scale_n=n)
            carried.__dict__.update({key: out.__dict__[key] for key in ("cov", "mean")
                                     if key in out.__dict__})
            return carried
        return out

    def with_obs_model(self, obs_model: ObservationModel) -> LatentPosterior:
        """The same belief (no cells) under another observation model of the same rank."""
        if obs_model.k != self.k:
            raise ModelError(f"obs_model has rank {obs_model.k}, the belief {self.k}")
        return LatentPosterior(obs_model, self.precision, self.shift, self.precision, self.shift)

    def __repr__(self) -> str:
        state = "flat" if self.is_flat else ("proper" if self.is_proper else "improper")
        return (f"LatentPosterior(k={self.k}, {state}, n_obs={self.cells.size}, "
                f"spatial={self.obs_model.is_spatial})")


def _innovation(P0: np.ndarray, h0: np.ndarray, G: np.ndarray, b: np.ndarray, zz: float,
                n: int) -> tuple[float, int]:
    """``(q, n_eff)`` of :meth:`LatentPosterior.innovation` from the prior's information form
    ``(P0, h0)`` and the observation terms ``G = Y W Y^T``, ``b = Y W z``, ``zz = z^T W z``
    (``W`` the inverse noise / spatial covariance): by Woodbury,
    ``q = (z - Y^T m)^T W (z - Y^T m) - r^T (P0 + G)^-1 r``, ``r = b - G m``, ``m`` the prior
    mean (0 along flat directions, which then cost one degree of freedom each)."""
    k = P0.shape[0]
    ev, U = np.linalg.eigh(symmetric_part(P0))
    top = max(float(ev[-1]), 0.0)
    ok = ev > _SINGULAR * top if top > 0 else np.zeros(k, dtype=bool)
    m = U[:, ok] @ ((U[:, ok].T @ h0) / ev[ok])
    r = b - G @ m
    P = symmetric_part(P0 + G)
    try:
        Lp = np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return float("nan"), 0
    w = scipy.linalg.solve_triangular(Lp, r, lower=True)
    q = zz - 2.0 * float(m @ b) + float(m @ G @ m) - float(w @ w)
    return max(q, 0.0), int(n - (k - int(ok.sum())))


def average_repeats(cells: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct cells and the mean of their values (for the spatial residual)."""
    uc, inv, cnt = np.unique(cells, return_inverse=True, return_counts=True)
    if uc.size == cells.size:
        order = np.argsort(cells, kind="stable")
        return cells[order], z[order]
    return uc, np.bincount(inv, weights=z, minlength=uc.size) / cnt


_average_repeats = average_repeats


def _predictive_std(obs: ObservationModel, var: np.ndarray, spatial: bool, idx: Any,
                    variance_scale: Any) -> np.ndarray:
    """Data-unit std of a new measurement from the latent variance ``var`` (fit units, at
    ``idx``; overwritten): plus the noise (the nugget with the spatial residual), times the
    belief's ``variance_scale`` (a scalar, or ``(m, 1)`` for ``m`` beliefs), times the scale
    and the calibration's per-cell ``interval_factor``."""
    if spatial:
        var += obs.spatial_cov.nugget
    else:
        nv = obs.without_spatial().noise_var
        var += nv if np.ndim(nv) == 0 else nv[idx]
    var *= variance_scale
    pstd = np.sqrt(var, out=var)
    if obs.scale is not None:
        pstd *= obs.scale[idx]
    if obs.interval_factor is not None:
        pstd *= obs.interval_factor[idx]
    return pstd


def predict_many(beliefs: Sequence[LatentPosterior], spatial: bool | None = None,
                 cells: Any = None, *, std: bool = True
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """Means and predictive stds ``(m, n)`` (data units) of ``m`` proper beliefs at ``cells``
    (default every cell): ``LatentPosterior.predict_all(spatial, cells)``'s first and last
    output for each belief, with ``std=False`` the means only.

    Beliefs updated from one prior at the same cells (one plan's test snapshots) differ only in
    their means: the latent variance and the kriging system depend on the cells alone. So it
    is computed once and the ``m`` residuals are kriged together, instead of ``m`` kriging
    passes. Other beliefs (different cells, averaged rows, a whole-grid FFT map) are predicted
    one by one; the result is the same either way."""
    beliefs = list(beliefs)
    if not beliefs:
        raise ModelError("predict_many needs at least one belief")
    b0 = beliefs[0]
    obs = b0.obs_model
    sp_ = b0._spatial(spatial)
    if cells is not None:
        cells = check_cells(cells, obs.n_cells)
    idx = slice(None) if cells is None else cells
    shared = all(b.obs_model is obs and (b.rows is None or b.rows.shape[0] == 0)
                 and np.array_equal(b.cells, b0.cells)
                 and np.array_equal(b.precision, b0.precision) for b in beliefs)
    if sp_:
        from .. import spatial as sp

        cov = obs.spatial_cov
    if shared and sp_:
        pairs = [_average_repeats(b.cells, obs.to_fit_units(b.cells, b.values))
                 for b in beliefs]
        uc = pairs[0][0]
        shared = not (cells is None and cov.metric == "grid" and cov.nugget > 0
                      and cov.sill > 0 and float(uc.size) * obs.n_cells > sp.FFT_KRIGE_MIN_WORK)
        zc = np.stack([z for _, z in pairs], axis=1)  # (n, m)
    if not shared:
        outs = [b.predict_all(sp_, cells) for b in beliefs]
        return (np.stack([o[0] for o in outs]),
                np.stack([o[2] for o in outs]) if std else None)
    Y = obs.Y if cells is None else obs.Y[:, cells]
    M = np.stack([b.mean for b in beliefs])  # (m, k)
    S = b0.cov
    mu = M @ Y
    if not sp_:
        var = np.maximum(np.einsum("ai,ai->i", Y, S @ Y), 0.0) if std else None
    else:
        Ys = obs.Y[:, uc]
        tg = np.arange(obs.n_cells) if cells is None else cells
        r_mu, var = sp.krige_core(
            cov, cov.points(obs.region, uc), zc - Ys.T @ M.T, cov.points(obs.region, tg),
            method="direct" if uc.size <= sp.MAX_DIRECT else "neighbors", neighbors=32,
            cutoff=1e-6, want_var=std, Ys=Ys, Yt=lambda sel: obs.Y[:, tg[sel]], cov_x=S)
        mu += r_mu
        var = np.maximum(var, 0.0) if std else None
    mean, _ = obs.to_data_units(mu, None, idx)
    if not std:
        return mean, None
    scales = np.array([b.variance_scale for b in beliefs])[:, None]
    return mean, _predictive_std(obs, np.broadcast_to(var, mu.shape).copy(), sp_, idx, scales)


# ============================================================================ model-level helpers
def _prior_name(prior: Any) -> str | None:
    """``None`` or ``"empirical"`` from a prior name (the registry's, when present)."""
    try:
        from ..registry import prior_value
    except ImportError:  # pragma: no cover - registry not there
        if prior in (None, "none", "empirical"):
            return None if prior in (None, "none") else "empirical"
        raise ModelError(f"prior must be one of [None, 'empirical'], got {prior!r}") from None
    return prior_value(prior)


def model_prior(model: Any, prior: str | None = None, ridge: float = 0.0,
                spatial: bool = False) -> LatentPosterior:
    """The belief ``GLRM.complete(prior=, ridge=, spatial=)`` folds in from.

    ``prior=None``: the paper's fold-in (flat, or the ridge prior ``N(0, ref_var / ridge I)``);
    ``"empirical"``: ``N(mean(X_), cov(X_))``, with ``ridge > 0`` adding ``ridge / ref_var I``
    to its precision. ``spatial`` switches the observation model's GP residual on.
    """
    prior = _prior_name(prior)
    ridge = check_positive(ridge, "ridge", error=ModelError)
    obs = ObservationModel.from_model(model, spatial=bool(spatial))
    if prior is None:
        return LatentPosterior.prior(obs, "ridge", ridge)
    base = LatentPosterior.prior(model, "empirical", spatial=bool(spatial))
    if ridge > 0:
        return LatentPosterior.from_moments(
            obs, base.mean, precision=base.precision + (ridge / obs.ref_var) * np.eye(obs.k))
    return base


def pattern_groups(observed: np.ndarray) -> list[list[int]]:
    """The rows of ``observed`` ``(n, m)`` (bool) grouped by their pattern, each group in row
    order: the snapshots that observe the same cells, for :func:`predict_many`."""
    groups: dict[bytes, list[int]] = {}
    for t, row in enumerate(np.packbits(observed, axis=1)):  # a loop over snapshots
        groups.setdefault(row.tobytes(), []).append(t)
    return list(groups.values())


def fold_in_maps(prior: LatentPosterior, V: np.ndarray, spatial: bool | None = None
                 ) -> np.ndarray:
    """The predicted maps ``(n, L)`` (data units) of :func:`fold_in_snapshots`, without the
    stds: the snapshots observed at the same cells (a placement's sensors) share one kriging
    system (:func:`predict_many`)."""
    V = np.asarray(V, dtype=np.float64)
    L = prior.obs_model.n_cells
    if V.ndim != 2 or V.shape[1] != L:
        raise DataError(f"values must have shape (n, {L}), got {V.shape}")
    observed = ~np.isnan(V)
    pred = np.empty(V.shape)
    for ts in pattern_groups(observed):
        cells = np.flatnonzero(observed[ts[0]])
        beliefs = [prior.update(cells, V[t, cells]) for t in ts]
        pred[ts] = predict_many(beliefs, spatial, std=False)[0]
    return pred


def fold_in_snapshots(prior: LatentPosterior, V: np.ndarray, spatial: bool | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fold each snapshot of ``V (n, L)`` (data units, NaN = not observed) into ``prior``.

    Returns ``pred (n, L)``, ``std (n, L)`` (posterior std of the latent value, data units),
    ``x (n, k)`` and the observation counts ``(n,)``. A snapshot whose observations do not
    determine ``x`` raises ModelError. (A loop over snapshots; never over cells.)
    """
    V = np.asarray(V, dtype=np.float64)
    L = prior.obs_model.n_cells
    if V.ndim != 2 or V.shape[1] != L:
        raise DataError(f"values must have shape (n, {L}), got {V.shape}")
    if np.isinf(V).any():
        raise DataError("observed values must be finite (NaN marks a cell not observed)")
    n = V.shape[0]
    pred = np.empty((n, L))
    std = np.empty((n, L))
    xs = np.empty((n, prior.k))
    counts = np.zeros(n, dtype=np.int64)
    for t in range(n):
        obs = np.flatnonzero(~np.isnan(V[t]))
        post = prior.update(obs, V[t, obs])
        counts[t] = obs.size
        pred[t], std[t] = post.predict(spatial)
        xs[t] = post.mean
    return pred, std, xs, counts
