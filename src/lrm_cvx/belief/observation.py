"""How a snapshot's values relate to its latent vector: :class:`ObservationModel` (the
observation half of :mod:`~lrm_cvx.belief.posterior`, which re-exports it).

For cell ``j``: ``value_j = offset_j + scale_j * (y_j^T x + r_j + e_j)``, ``e_j ~ N(0,
noise_var_j)``, ``r ~ GP(spatial_cov)`` optional (then ``e`` is the covariance's nugget). The
model maps values to fit units and back and gives the information terms ``Y_S W Y_S^T``,
``Y_S W z_S`` of a set of observations (``W`` the inverse noise, or the inverse GP covariance
with the spatial residual: generalised least squares), for point and averaged observations.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse as sps
from scipy.spatial.distance import cdist

from ..errors import DataError, ModelError
from .averaged import fit_rows, row_terms

__all__ = ["ObservationModel", "NOISE_FLOOR"]

NOISE_FLOOR = 1e-30  # a fitted noise of exactly 0 (rank = T): a tiny stand-in, not a division by 0
_NOISE_FLOOR = NOISE_FLOOR


# ============================================================================ observation model
@dataclass(frozen=True, eq=False)
class ObservationModel:
    """How a snapshot's values relate to its latent vector ``x (k,)``: for cell ``j``,
    ``value_j = offset_j + scale_j * (y_j^T x + r_j + e_j)``, ``e_j ~ N(0, noise_var_j)``,
    ``r ~ GP(spatial_cov)`` (optional; then ``e`` is the covariance's nugget).

    ``Y (k, L)``; ``offset``/``scale`` ``(L,)`` data units or None; ``noise_var`` a scalar or
    ``(L,)`` (fit units, > 0); ``spatial_cov`` a :class:`~lrm_cvx.spatial.ResidualCovariance`
    (fit units) or None; ``region`` the cells' Region (needed with ``spatial_cov``);
    ``ref_var`` the global noise variance that scales a ridge prior ``N(0, ref_var / ridge I)``
    (default: ``spatial_cov.total_variance`` when spatial, else the mean of ``noise_var``).
    ``interval_factor`` ``(L,)`` (> 0) or None: a per-cell factor of the predictive std only
    (a calibration's locally weighted intervals, ``Calibration.local_power``); the means,
    latent stds and plans do not see it.
    """

    Y: np.ndarray
    offset: np.ndarray | None = None
    scale: np.ndarray | None = None
    noise_var: Any = 1.0
    spatial_cov: Any = None
    region: Any = None
    ref_var: float | None = None
    variance_scale: float = 1.0  # calibration (validation.calibration): multiplies output variances
    adaptive_dof: float | None = None  # calibration: prior dof of the per-snapshot scale
    scale_discount: float = 0.0  # calibration: weight per step of earlier snapshots' evidence
    calibration: Any = None  # the model's Calibration (conformal interval multipliers), or None
    interval_factor: np.ndarray | None = None  # calibration: per-cell factor of predictive stds

    def __post_init__(self) -> None:
        Y = np.asarray(self.Y)
        if Y.ndim != 2 or not (np.issubdtype(Y.dtype, np.floating)
                               or np.issubdtype(Y.dtype, np.integer)):
            raise DataError(f"Y must be a (k, L) numeric matrix, got {Y.dtype} {Y.shape}")
        Y = np.ascontiguousarray(Y, dtype=np.float64)
        k, L = Y.shape
        object.__setattr__(self, "Y", Y)
        for name in ("offset", "scale"):
            v = getattr(self, name)
            if v is None:
                continue
            v = np.asarray(v, dtype=np.float64)
            if v.shape != (L,) or not np.all(np.isfinite(v)):
                raise ModelError(f"{name} must be a finite ({L},) array, got shape {v.shape}")
            if name == "scale" and np.any(v <= 0):
                raise ModelError("scale must be > 0 at every cell")
            object.__setattr__(self, name, v)
        if self.interval_factor is not None:
            v = np.asarray(self.interval_factor, dtype=np.float64)
            if v.shape != (L,) or not np.all(np.isfinite(v) & (v > 0)):
                raise ModelError(f"interval_factor must be a ({L},) array of finite numbers > 0, "
                                 f"got shape {v.shape}")
            object.__setattr__(self, "interval_factor", v)
        nv = np.asarray(self.noise_var, dtype=np.float64)
        if nv.ndim not in (0,) and nv.shape != (L,):
            raise ModelError(f"noise_var must be a scalar or ({L},), got shape {nv.shape}")
        if not np.all(np.isfinite(nv)) or np.any(nv < 0):
            raise ModelError("noise_var must be finite and >= 0")
        nv = np.maximum(nv, _NOISE_FLOOR)
        object.__setattr__(self, "noise_var", float(nv) if nv.ndim == 0 else nv)
        for name in ("variance_scale", "adaptive_dof"):
            val = getattr(self, name)
            if val is None and name == "adaptive_dof":
                continue
            if not (np.isfinite(val) and val > 0):
                raise ModelError(f"{name} must be a finite number > 0, got {val!r}")
        if not 0.0 <= float(self.scale_discount) <= 1.0:
            raise ModelError(f"scale_discount must be in [0, 1], got {self.scale_discount!r}")
        if self.spatial_cov is not None:
            from ..spatial import ResidualCovariance

            if not isinstance(self.spatial_cov, ResidualCovariance):
                raise ModelError("spatial_cov must be a ResidualCovariance, got "
                                 f"{type(self.spatial_cov).__name__}")
            if self.region is None or getattr(self.region, "n_cells", None) != L:
                raise ModelError(f"a spatial observation model needs the region of the {L} cells")
        if self.ref_var is None:
            ref = (self.spatial_cov.total_variance if self.spatial_cov is not None
                   else float(np.mean(nv)))
            object.__setattr__(self, "ref_var", max(float(ref), _NOISE_FLOOR))

    @classmethod
    def from_model(cls, model: Any, spatial: bool | None = None) -> ObservationModel:
        """The observation model of a fitted :class:`~lrm_cvx.glrm.GLRM`: its ``Y_``,
        ``offset_``, ``scale_``, ``noise_var_`` (else ``noise_std_^2``), and with ``spatial``
        (None: whenever the model has one) its ``spatial_cov_`` and region."""
        model._check_fitted()
        cov = getattr(model, "spatial_cov_", None)
        if spatial is None:
            spatial = cov is not None
        if spatial and cov is None:
            raise ModelError("spatial=True needs a model fitted with spatial='exponential' "
                             "(or another covariance model)")
        nv = getattr(model, "noise_var_", None)
        sigma2 = float(model.noise_std_) ** 2
        from ..glrm.calibrated import interval_factor, residual_factor

        rho = residual_factor(model)
        if rho != 1.0:  # a new snapshot's, validated (selection, calibration): the variances
            sigma2 *= rho
            nv = None if nv is None else np.asarray(nv, dtype=np.float64) * rho
            if cov is not None:
                cov = replace(cov, sill=cov.sill * rho, nugget=cov.nugget * rho)
        return cls(Y=model.Y, offset=getattr(model, "offset_", None),
                   scale=getattr(model, "scale_", None),
                   noise_var=sigma2 if nv is None else nv,
                   spatial_cov=cov if spatial else None,
                   region=model.region_ if spatial else None,
                   ref_var=cov.total_variance if spatial else max(sigma2, _NOISE_FLOOR),
                   variance_scale=_variance_scale(model),
                   adaptive_dof=_adaptive_dof(model),
                   scale_discount=_scale_discount(model),
                   calibration=getattr(model, "calibration_", None),
                   interval_factor=interval_factor(model))

    # ------------------------------------------------------------------ helpers
    @property
    def k(self) -> int:
        return self.Y.shape[0]

    @property
    def n_cells(self) -> int:
        return self.Y.shape[1]

    @property
    def is_spatial(self) -> bool:
        return self.spatial_cov is not None

    @property
    def is_plain(self) -> bool:
        """No offset, scale, per-cell noise or spatial residual: the paper's model."""
        return (self.offset is None and self.scale is None and np.ndim(self.noise_var) == 0
                and self.spatial_cov is None)

    def without_spatial(self) -> ObservationModel:
        """The same model without the spatial residual (independent noise ``noise_var``)."""
        if not self.is_spatial:
            return self
        return replace(self, spatial_cov=None, region=None, ref_var=None)

    def to_fit_units(self, cells: np.ndarray, values: np.ndarray) -> np.ndarray:
        """``(values - offset[cells]) / scale[cells]`` (float64)."""
        z = np.asarray(values, dtype=np.float64)
        if self.offset is not None:
            z = z - self.offset[cells]
        if self.scale is not None:
            z = z / self.scale[cells]
        return z

    def to_data_units(self, mean: np.ndarray, std: np.ndarray | None = None,
                      cells: Any = slice(None)) -> tuple[np.ndarray, np.ndarray | None]:
        """Map fit-unit means (and stds) at ``cells`` back to data units."""
        if self.scale is not None:
            mean = mean * self.scale[cells]
            std = None if std is None else std * self.scale[cells]
        if self.offset is not None:
            mean = mean + self.offset[cells]
        return mean, std

    def noise_at(self, cells: np.ndarray) -> np.ndarray:
        """Independent noise variance of one measurement at ``cells`` (fit units)."""
        if self.is_spatial:
            return np.full(len(cells), float(self.spatial_cov.nugget))
        nv = self.noise_var
        return np.full(len(cells), nv) if np.ndim(nv) == 0 else nv[cells]

    def observation_terms(self, cells: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(Y_S W Y_S^T (k, k), Y_S W z (k,))`` of observations ``z`` (fit units) at ``cells``:
        ``W = diag(1 / noise_var)``, or ``C^-1`` with the spatial residual (GLS; the cells must
        then be distinct)."""
        return self._terms(cells, z)[:2]

    def fit_rows(self, rows: sps.csr_matrix, values: np.ndarray, errors: str = "independent"
                 ) -> tuple[sps.csr_matrix, np.ndarray, np.ndarray]:
        """Averaged observations in fit units ``(B, z, noise)``
        (:func:`~lrm_cvx.belief.averaged.fit_rows`; the nugget with the spatial residual)."""
        nv = self.spatial_cov.nugget if self.is_spatial else self.noise_var
        return fit_rows(rows, values, self.offset, self.scale, nv, errors)

    def row_terms(self, B: sps.csr_matrix, z: np.ndarray, noise: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, float]:
        """``(Yr W Yr^T, Yr W z, z^T W z)`` of averaged observations ``z = B f + e`` (fit units;
        :func:`~lrm_cvx.belief.averaged.row_terms`)."""
        return row_terms(self.Y, B, z, noise, self.spatial_cov, self.region)

    def _terms(self, cells: np.ndarray, z: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, float]:
        """:meth:`observation_terms` and ``z^T W z``."""
        Ys = self.Y[:, cells]
        if not self.is_spatial:
            w = 1.0 / self.noise_at(cells)
            Yw = Ys * w
            return Yw @ Ys.T, Yw @ z, float(z @ (w * z))
        from .. import spatial as sp

        cov = self.spatial_cov
        xyz = cov.points(self.region, cells)
        C = cov.covariance(sp.arc_distance(cdist(xyz, xyz), cov.metric), nugget=False)
        C[np.diag_indices_from(C)] = cov.total_variance
        Lc = sp.jittered_cholesky(C, cov.total_variance, "observation")
        Ws = scipy.linalg.solve_triangular(Lc, Ys.T, lower=True)
        zs = scipy.linalg.solve_triangular(Lc, z, lower=True)
        return Ws.T @ Ws, Ws.T @ zs, float(zs @ zs)


# ====================================================== the model's calibration
def _adaptive_dof(model: Any) -> float | None:
    """The calibration's prior degrees of freedom of the per-snapshot scale (None: fixed)."""
    cal = getattr(model, "calibration_", None)
    return None if cal is None else getattr(cal, "dof", None)


def _scale_discount(model: Any) -> float:
    """The calibration's per-step discount of earlier snapshots' scale evidence (0: none)."""
    cal = getattr(model, "calibration_", None)
    return 0.0 if cal is None else float(getattr(cal, "discount", 0.0) or 0.0)


def _variance_scale(model: Any, temporal: bool = False) -> float:
    """The model's calibrated variance scale (``calibration_``; 1.0 when not calibrated)."""
    from ..glrm.calibrated import variance_scale

    return variance_scale(model, temporal)
