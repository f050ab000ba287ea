"""A model's calibration as it is stored and applied (the estimation is glrm/calibration.py).

:class:`Calibration` holds the variance scales (``calibration_`` on a model, NetCDF attributes
``calibration_*``); :func:`variance_scale`, :func:`noise_variance`, :func:`predictive_std` and
:func:`interval_coverage` are what every predictive variance and coverage reads. They sit below
the posterior and the model, which read them, while the estimation refits models and runs the
filter above them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..errors import ModelError

__all__ = ["Calibration", "variance_scale", "noise_variance", "predictive_std",
           "interval_coverage"]

_PREFIX = "calibration_"


@dataclass(frozen=True)
class Calibration:
    """Variance scales of a model's predictive distribution, estimated by cross-validation.

    ``scale``: multiplier of the memoryless fold-in's predictive variance; ``temporal_scale``:
    of the filter's (None when not estimated: the filter then uses ``scale``). ``dof``: prior
    degrees of freedom of the per-snapshot scale (None: the scale is fixed); with it each
    snapshot's variances are scaled by ``(dof * scale + q) / (dof + n)``, ``q`` the squared
    norm of the standardized innovations of its ``n`` observations
    (:meth:`~lrm_cvx.glrm.posterior.LatentPosterior.innovation`), plus the earlier snapshots'
    ``q`` and ``n`` weighted by ``discount`` per step (0: each snapshot on its own; carried by
    ``MonitorState``). ``dof_loglik_gain``: the cross-validated Gaussian log-likelihood per
    residual gained over the fixed scale. ``n_residuals``
    and ``coverage68_raw`` / ``coverage95_raw`` (the cross-validated coverage before scaling)
    document the estimate; ``n_blocks`` and ``sizes`` how it was made.
    """

    scale: float = 1.0
    temporal_scale: float | None = None
    n_residuals: int = 0
    coverage68_raw: float = float("nan")
    coverage95_raw: float = float("nan")
    temporal_coverage68_raw: float = float("nan")
    temporal_coverage95_raw: float = float("nan")
    n_blocks: int = 0
    sizes: str = ""
    dof: float | None = None
    discount: float = 0.0
    residual_scale: float = 1.0
    dof_loglik_gain: float = 0.0

    def __post_init__(self) -> None:
        for name in ("scale", "temporal_scale", "dof", "residual_scale"):
            v = getattr(self, name)
            if v is None:
                continue
            if not (np.isfinite(v) and v > 0):
                raise ModelError(f"Calibration.{name} must be a finite number > 0, got {v!r}")
            object.__setattr__(self, name, float(v))

    def variance_scale(self, temporal: bool = False) -> float:
        """The scale for the memoryless fold-in or (``temporal=True``) the filter."""
        if temporal and self.temporal_scale is not None:
            return self.temporal_scale
        return self.scale

    def to_attrs(self) -> dict[str, Any]:
        """Flat NetCDF attributes ``calibration_*`` (None stored as NaN)."""
        out = {}
        for key, value in asdict(self).items():
            out[_PREFIX + key] = float("nan") if value is None else value
        return out

    @classmethod
    def from_attrs(cls, attrs: dict[str, Any]) -> Calibration | None:
        """The calibration stored by :meth:`to_attrs`, or None when ``attrs`` hold none."""
        if _PREFIX + "scale" not in attrs:
            return None
        kw: dict[str, Any] = {}
        for key in cls.__dataclass_fields__:
            if _PREFIX + key in attrs:
                v = attrs[_PREFIX + key]
                if key in ("temporal_scale", "dof"):
                    v = None if not np.isfinite(float(v)) else float(v)
                elif key in ("n_residuals", "n_blocks"):
                    v = int(v)
                elif key == "sizes":
                    v = str(v)
                else:
                    v = float(v)
                kw[key] = v
        return cls(**kw)


# ----------------------------------------------------------------------------- applying it
def variance_scale(model: Any, temporal: bool = False) -> float:
    """The model's calibrated variance scale (1.0 when it was not calibrated)."""
    cal = getattr(model, "calibration_", None)
    return 1.0 if cal is None else cal.variance_scale(temporal)


def noise_variance(model: Any, spatial: bool = False) -> Any:
    """Variance of a new measurement around the latent value, in data units: the spatial
    nugget with ``spatial=True``, else ``noise_var_`` (per cell) or ``noise_std_^2``, times
    ``scale_^2`` when the model was fitted with ``scale``. A scalar or ``(L,)``."""
    if spatial:
        cov = getattr(model, "spatial_cov_", None)
        if cov is None:
            raise ModelError("spatial=True needs a model fitted with spatial=...")
        nv: Any = float(cov.nugget)
    else:
        nv = getattr(model, "noise_var_", None)
        nv = float(model.noise_std_) ** 2 if nv is None else np.asarray(nv, dtype=np.float64)
    sc = getattr(model, "scale_", None)
    return nv if sc is None else nv * np.asarray(sc, dtype=np.float64) ** 2


def predictive_std(model: Any, std: Any, spatial: bool = False,
                   temporal: bool = False) -> np.ndarray:
    """Calibrated std of a new measurement: ``sqrt(std^2 + s * noise)``.

    ``std`` ``(..., L)`` (data units) is the posterior std of the latent value as returned by
    ``complete`` / ``MonitorState.predict`` (which already carry the scale ``s``: the
    observation model's ``variance_scale``); ``noise`` is :func:`noise_variance`; ``s`` the
    model's :func:`variance_scale`. Equals ``LatentPosterior.predictive_std``.
    """
    s = np.asarray(std, dtype=np.float64)
    return np.sqrt(s * s + variance_scale(model, temporal) * noise_variance(model, spatial))


def interval_coverage(values: Any, mean: Any, std: Any,
                      levels: Sequence[float] = (0.68, 0.95)) -> np.ndarray:
    """Fraction of the finite ``values`` inside ``mean +- z_level * std`` per level.

    ``values``, ``mean``, ``std`` broadcast together; NaN values are left out. Returns
    ``(len(levels),)`` (NaN when no value is finite).
    """
    from scipy.stats import norm

    v = np.asarray(values, dtype=np.float64)
    m = np.asarray(mean, dtype=np.float64)
    sd = np.asarray(std, dtype=np.float64)
    z = np.abs(v - m) / np.where(sd > 0, sd, np.nan)
    z = z[np.isfinite(v)]
    if z.size == 0:
        return np.full(len(levels), np.nan)
    z = np.where(np.isnan(z), np.inf, z)
    return np.array([float(np.mean(z <= norm.ppf(0.5 + lv / 2))) for lv in levels])
