"""Spatial residual model: low-rank trend plus a stationary Gaussian-process residual.

:mod:`.covariance` holds the covariance model and its fit to the training residuals,
:mod:`.kriging` the kriging of residuals, the FFT convolution and the GP criterion's model. The
fold-ins that use the GP residual live in :mod:`lrm_cvx.belief.foldin`. docs/spatial.md describes
the model, its metrics and how it scales.
"""

from __future__ import annotations

from .covariance import (
    KERNEL_REGISTRY,
    MODELS,
    EmpiricalVariogram,
    ResidualCovariance,
    arc_distance,
    cell_xyz,
    correlation,
    empirical_variogram,
    estimate_anisotropy,
    fit_residual_covariance,
)
from .covariance import cell_xyz as _coords  # noqa: F401  (private names the tests use)
from .kriging import (
    FFT_KRIGE_MIN_WORK,
    FFT_KRIGE_VAR_TOL,
    MAX_DIRECT,
    GridConv,
    check_gp_inputs,
    gp_latent_cov,
    gp_noise,
    jittered_cholesky,
    krige,
    krige_core,
    krige_grid_fft,
    krige_many,
)
from .kriging import krige_core as _krige_core  # noqa: F401

__all__ = [
    "MODELS",
    "KERNEL_REGISTRY",
    "ResidualCovariance",
    "EmpiricalVariogram",
    "correlation",
    "empirical_variogram",
    "estimate_anisotropy",
    "fit_residual_covariance",
    "krige",
    "krige_many",
    "krige_grid_fft",
    "krige_core",
    "cell_xyz",
    "arc_distance",
    "jittered_cholesky",
    "MAX_DIRECT",
    "FFT_KRIGE_MIN_WORK",
    "FFT_KRIGE_VAR_TOL",
    "GridConv",
    "gp_noise",
    "gp_latent_cov",
    "check_gp_inputs",
]

